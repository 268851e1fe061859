"""lfd_torch: robust robot learning from demonstration in PyTorch.

Reproduces Wang, Zeng et al., "A Novel Robust Imitation Learning Framework for Complex Skills With Limited
Demonstrations" (IEEE T-ASE 2024): preprocessing, BP-GM-HMM segmentation, stable LPV-DS/SEDS primitives,
a behavior-tree skill engine with disturbance modulation, metrics and experiments.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lfd_torch")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from lfd_torch.store.paths import register_resolvers as _register_resolvers

_register_resolvers()  # ${lfd_root:} in the Hydra configs (conf/paths)

__all__ = ["__version__", "data", "ds", "errors", "gmm", "metrics", "modulation", "preprocess", "robot", "rollout", "segmentation", "skills", "store", "utils", "viz"]
