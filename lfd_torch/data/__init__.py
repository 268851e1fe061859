"""Demonstration containers and loaders.

Notation: B demonstrations, T padded samples, d state dimensions. See :mod:`lfd_torch.data.demos`.
"""

from lfd_torch.data.demos import MIN_SAMPLES, Demos
from lfd_torch.data.finite_difference import finite_difference
from lfd_torch.data.lasa import LASA_MULTI_NAMES, LASA_NAMES, LASA_SINGLE_NAMES, lasa_data_dir, load_lasa

__all__ = [
    "Demos",
    "MIN_SAMPLES",
    "finite_difference",
    "LASA_NAMES",
    "LASA_SINGLE_NAMES",
    "LASA_MULTI_NAMES",
    "lasa_data_dir",
    "load_lasa",
]
