"""Demonstration containers and loaders.

Notation: B demonstrations, T padded samples, d state dimensions. See :mod:`lfd_torch.data.demos`.
"""

from lfd_torch.data.demos import MIN_SAMPLES, Demos
from lfd_torch.data.finite_difference import finite_difference
from lfd_torch.data.lasa import LASA_MULTI_NAMES, LASA_NAMES, LASA_SINGLE_NAMES, lasa_data_dir, load_lasa
from lfd_torch.data.mnist import (
    MNIST_ENV,
    MNIST_SPLITS,
    Stroke,
    extract_stroke,
    load_mnist,
    mnist_demos,
    mnist_dir,
    mnist_files,
    read_idx,
    stroke_trajectory,
)

__all__ = [
    "Demos",
    "MIN_SAMPLES",
    "finite_difference",
    "LASA_NAMES",
    "LASA_SINGLE_NAMES",
    "LASA_MULTI_NAMES",
    "lasa_data_dir",
    "load_lasa",
    "MNIST_ENV",
    "MNIST_SPLITS",
    "Stroke",
    "extract_stroke",
    "load_mnist",
    "mnist_demos",
    "mnist_dir",
    "mnist_files",
    "read_idx",
    "stroke_trajectory",
]
