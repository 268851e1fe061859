"""Command-line entry point: ``python -m lfd_torch.store.collect SWEEP_DIR [--pattern GLOB] [--out FILE ...]``.

Merges the per-job results tables of a sweep (see :mod:`lfd_torch.store.sweep`). In Python, use
:func:`lfd_torch.store.collect`, which this module only wraps; do not import this module (importing it
rebinds the package attribute ``lfd_torch.store.collect`` to the module).
"""

import sys

from lfd_torch.store.sweep import main

if __name__ == "__main__":
    sys.exit(main())
