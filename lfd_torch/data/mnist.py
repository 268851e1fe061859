"""MNIST handwritten digits (LeCun, Cortes, Burges) as 2-D pen-stroke demonstrations (paper Sec. V-A, Figs 10-11).

Reading. :func:`load_mnist` reads the images and labels of one split from IDX files (gzip-compressed or raw) in a
directory given as an argument or by the environment variable ``LFD_MNIST_DIR``; the directory itself, its
``raw/`` and its ``MNIST/raw/`` sub-folders (torchvision's layout) are searched for ``t10k-images-idx3-ubyte[.gz]``,
``t10k-labels-idx1-ubyte[.gz]`` (split ``test``) or ``train-...`` (split ``train``). Nothing is downloaded. A missing
directory, a missing file (the message lists every path looked for), or a file whose IDX magic number, dimensions
or size is wrong raises :class:`~lfd_torch.errors.StoreError`.

Stroke extraction (:func:`extract_stroke`), per H x W uint8 image:

1. Binarise: bilinear upsampling by ``upsample`` (a smoother skeleton), threshold at ``threshold`` x 255; keep the
   largest 8-connected component (a digit written in two strokes keeps its main one), fill holes smaller than
   ``min_hole`` px^2 (ink blots, not loops).
2. Skeletonise (scikit-image ``skeletonize``) and build the 8-connected pixel graph (a diagonal link is dropped
   where the two pixels are also joined through a 4-neighbour, so that lines have no triangles); contract it to a
   multigraph whose nodes are endpoints and junction clusters and whose edges are pixel chains; prune terminal
   spurs shorter than ``prune`` px, again until none is left; junctions joined by a branch shorter than ``merge``
   px become one node (a crossing that skeletonisation split in two).
3. The pen path is the longest *trail* (a walk that uses each skeleton branch at most once, but may pass a junction
   twice -- the crossing of an 8, the closing point of a 6 or 9) that starts at an endpoint, found by exhaustive
   search over the (small) branch graph. Up to ``excursions`` dead-end branches may be drawn out and back (a sharp
   return: the stem of a 4 above its bar). Score: ``length - turn_weight * turning + height_weight * |drop|``
   (px; turning in rad at junctions, pi at a sharp return; drop = height between start and end): ties between
   trails of equal length (the two ways round a loop) go to the smoother one, then to the one running top to
   bottom. A skeleton without endpoints (a closed 0 or 8) starts at its top-most pixel (left-most among ties) and
   is traversed counter-clockwise there (first move to the left, as a 0 is written); the closed trail is then cut
   open by dropping its last ``loop_gap`` fraction, so the pen's end (the attractor) differs from its start. A
   trail that does not come back to its start (a theta whose bar ends it) keeps its start at the top pixel and
   the direction of the trail search.
4. Orientation: the attractor is the last point. An open trail starts at its higher end (natural writing starts
   at the top); ends within ``level_tol`` px of the same height start at the left-most one.
5. Gaussian smoothing along the path (``smooth`` px), then resampling.

:func:`mnist_demos` turns several images of one digit into :class:`~lfd_torch.data.Demos`: coordinates x to the
right and y up, ``mm_per_pixel`` mm per image pixel (default 2.25: MNIST's 20 px digit box spans 45 mm, like a
LASA shape), translated so that every demonstration ends at the origin (the attractor), traversed with a
minimum-jerk time law at mean speed ``mean_speed`` mm/s (rest at both ends and at every cusp, where the pen
reverses; durations of a few seconds), sampled at ``n_points`` equal time steps; velocities are the analytic
derivative of the time law (mm/s). With ``consistent`` the open strokes whose ends are level (where the rule of step
4 falls back on left-most, a fragile choice) are re-oriented to agree with the set's medoid (DTW of both
directions); the others keep the top-to-bottom rule.
"""

from __future__ import annotations

import functools
import gzip
import inspect
import logging
import math
import os
import struct
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.ndimage
import torch
from torch import Tensor

from lfd_torch.data.demos import Demos
from lfd_torch.errors import (
    InvalidArgumentError,
    NonFiniteError,
    ShapeMismatchError,
    StoreError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.utils import check_cost, check_float, check_int, check_path, real_array, resolve_device, resolve_dtype

__all__ = [
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

log = logging.getLogger(__name__)

#: Environment variable naming the directory of the IDX files when no directory is passed.
MNIST_ENV = "LFD_MNIST_DIR"

#: Bounds that keep the cost of :func:`mnist_demos` finite: images read (n_demos, pool) and points per stroke.
MAX_IMAGES = 70_000
MAX_POINTS = 1_000_000
MAX_UPSAMPLE = 64
#: Split name -> file prefix of the standard distribution.
MNIST_SPLITS: dict[str, str] = {"test": "t10k", "train": "train"}

_IDX_TYPES: dict[int, np.dtype] = {
    0x08: np.dtype(np.uint8), 0x09: np.dtype(np.int8), 0x0B: np.dtype(">i2"), 0x0C: np.dtype(">i4"),
    0x0D: np.dtype(">f4"), 0x0E: np.dtype(">f8"),
}  # fmt: skip
_IMAGES_MAGIC = 0x00000803  # uint8, 3 dimensions (N, rows, cols)
_LABELS_MAGIC = 0x00000801  # uint8, 1 dimension (N,)
_SUBDIRS = (".", "raw", os.path.join("MNIST", "raw"))
_MIN_SIDE, _MAX_SIDE = 8, 1024


# ============================================================================================== IDX files
def read_idx(path: str | os.PathLike[str]) -> np.ndarray:
    """Read one IDX file (``.gz`` is decompressed) as a read-only numpy array of its declared type and dimensions.

    Raises:
        StoreError: unreadable or corrupt gzip; a header that is not IDX (two zero bytes, a known type code, at least
            one dimension); fewer or more data bytes than the dimensions declare.
    """
    path = check_path(path, "path", error=StoreError)
    try:
        if path.name.endswith(".gz"):
            with gzip.open(path, "rb") as f:
                data = f.read()
        else:
            data = path.read_bytes()
    except (OSError, EOFError, zlib.error) as exc:  # gzip.BadGzipFile is an OSError
        raise StoreError(f"cannot read IDX file {path}: {exc}") from exc
    if len(data) < 4:
        raise StoreError(f"{path}: {len(data)} bytes, too short for an IDX header (4-byte magic number)")
    if data[0] != 0 or data[1] != 0 or data[2] not in _IDX_TYPES or data[3] == 0:
        raise StoreError(f"{path} is not an IDX file: magic number 0x{data[:4].hex()} (expected 0x0000TTNN)")
    ndim = data[3]
    header = 4 + 4 * ndim
    if len(data) < header:
        raise StoreError(f"{path} is truncated: {len(data)} bytes, its header needs {header}")
    dims = struct.unpack(f">{ndim}I", data[4:header])
    dtype = _IDX_TYPES[data[2]]
    count = math.prod(dims)
    need = header + count * dtype.itemsize
    if len(data) != need:
        what = "truncated" if len(data) < need else "longer than its header declares"
        raise StoreError(f"{path} is {what}: {len(data)} bytes, dimensions {list(dims)} need {need}")
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=header).reshape(dims)
    arr.setflags(write=False)
    return arr


def _magic(arr_path: Path) -> int:
    opener = gzip.open if arr_path.name.endswith(".gz") else open
    try:
        with opener(arr_path, "rb") as f:
            head = f.read(4)
    except (OSError, EOFError, zlib.error) as exc:
        raise StoreError(f"cannot read IDX file {arr_path}: {exc}") from exc
    return int.from_bytes(head, "big") if len(head) == 4 else -1


def mnist_dir(directory: str | os.PathLike[str] | None = None) -> Path:
    """The MNIST directory: ``directory`` if given, else ``$LFD_MNIST_DIR``.

    Raises:
        StoreError: neither is set, or the directory does not exist.
    """
    source = "directory argument"
    if directory is not None and (isinstance(directory, bytes) or not isinstance(directory, (str, os.PathLike))):
        raise StoreError(f"MNIST directory must be a path (str or os.PathLike) or None, got {directory!r}")
    if directory is None or str(directory) == "":
        env = os.environ.get(MNIST_ENV, "")
        if not env:
            raise StoreError(
                f"no MNIST directory: pass directory=... (config key data.directory) or set {MNIST_ENV} to a folder "
                "holding the IDX files (t10k-images-idx3-ubyte[.gz], ...); nothing is downloaded"
            )
        directory, source = env, f"${MNIST_ENV}"
    path = Path(directory).expanduser()
    if not path.is_dir():
        raise StoreError(f"MNIST directory {path} (from the {source}) does not exist or is not a directory")
    return path


def mnist_files(split: str = "test", directory: str | os.PathLike[str] | None = None) -> tuple[Path, Path]:
    """(images, labels) paths of ``split`` in the MNIST directory (see the module docstring for the search).

    Both files come from the same folder; an uncompressed file is preferred to its ``.gz``.

    Raises:
        UnknownNameError: ``split`` is not ``test`` or ``train``.
        StoreError: no directory, or no folder holding both files (the message lists every path looked for).
    """
    if split not in MNIST_SPLITS:
        raise UnknownNameError("MNIST split", repr(split), tuple(MNIST_SPLITS))
    root = mnist_dir(directory)
    prefix = MNIST_SPLITS[split]
    looked: list[str] = []
    for sub in _SUBDIRS:
        folder = (root / sub) if sub != "." else root
        found = []
        for kind in ("images-idx3", "labels-idx1"):
            hit = None
            for name in (f"{prefix}-{kind}-ubyte", f"{prefix}-{kind}-ubyte.gz"):
                candidate = folder / name
                looked.append(str(candidate))
                if hit is None and candidate.is_file():
                    hit = candidate
            found.append(hit)
        if found[0] is not None and found[1] is not None:
            return found[0], found[1]
    raise StoreError(f"no MNIST {split} images and labels found; looked for: {', '.join(looked)}")


@functools.lru_cache(maxsize=4)
def _read_pair(images: str, labels: str, stamp: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    del stamp  # part of the cache key only: a rewritten file is read again
    ipath, lpath = Path(images), Path(labels)
    for p, magic, what in ((ipath, _IMAGES_MAGIC, "images (uint8, 3 dimensions)"),
                           (lpath, _LABELS_MAGIC, "labels (uint8, 1 dimension)")):  # fmt: skip
        m = _magic(p)
        if m != magic:
            raise StoreError(f"{p}: magic number 0x{max(m, 0):08x}, expected 0x{magic:08x} for MNIST {what}")
    x = read_idx(ipath)
    y = read_idx(lpath)
    n, rows, cols = x.shape
    if not (_MIN_SIDE <= rows <= _MAX_SIDE and _MIN_SIDE <= cols <= _MAX_SIDE):
        raise StoreError(f"{ipath}: images of {rows} x {cols} pixels; MNIST images are 28 x 28 (8..1024 accepted)")
    if y.shape[0] != n:
        raise StoreError(f"{ipath} holds {n} images but {lpath} holds {y.shape[0]} labels")
    if n and int(y.max()) > 9:
        raise StoreError(f"{lpath}: label {int(y.max())} outside 0..9")
    return x, y


def load_mnist(
    split: str = "test", directory: str | os.PathLike[str] | None = None
) -> tuple[Tensor, Tensor]:
    """Images (N, H, W) uint8 (0 = background, 255 = ink) and labels (N,) int64 of one MNIST split.

    Args:
        split: ``test`` (t10k, 10,000 images) or ``train`` (60,000).
        directory: folder of the IDX files; None reads ``$LFD_MNIST_DIR``.

    Raises:
        UnknownNameError: unknown ``split``.
        StoreError: missing directory or files (listing the paths looked for), or a bad file: wrong magic number,
            dimensions, size, or label count.
    """
    images, labels = mnist_files(split, directory)
    si, sl = images.stat(), labels.stat()
    x, y = _read_pair(str(images), str(labels), (si.st_mtime_ns, si.st_size, sl.st_mtime_ns, sl.st_size))
    return torch.from_numpy(x.copy()), torch.from_numpy(y.astype(np.int64))


# ============================================================================================== skeleton graph
_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def _adjacency(skel: np.ndarray) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """8-connected neighbours of every skeleton pixel, without diagonals that a 4-neighbour already bridges."""
    H, W = skel.shape
    pix = [tuple(p) for p in np.argwhere(skel)]
    on = skel

    def lit(r: int, c: int) -> bool:
        return 0 <= r < H and 0 <= c < W and bool(on[r, c])

    adj: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r, c in pix:
        nb = []
        for dr, dc in _NEIGHBOURS:
            if not lit(r + dr, c + dc):
                continue
            if dr and dc and (lit(r + dr, c) or lit(r, c + dc)):
                continue
            nb.append((r + dr, c + dc))
        adj[(r, c)] = nb
    return adj


@dataclass
class _Edge:
    u: int
    v: int
    chain: list[tuple[int, int]]  # pixels from u's pixel to v's pixel
    length: float  # px (upsampled grid)


def _graph(
    adj: dict[tuple[int, int], list[tuple[int, int]]], extra_node: tuple[int, int] | None = None
) -> tuple[dict[tuple[int, int], int], list[_Edge]]:
    """Contract the pixel graph: node clusters (pixel -> node id) and edges (pixel chains between nodes)."""
    node_pix = {p for p, nb in adj.items() if len(nb) != 2}
    cluster: dict[tuple[int, int], int] = {}
    n = 0
    for p in sorted(node_pix):
        if p in cluster:
            continue
        stack = [p]
        cluster[p] = n
        while stack:
            q = stack.pop()
            for s in adj[q]:
                if s in node_pix and s not in cluster:
                    cluster[s] = n
                    stack.append(s)
        n += 1
    if extra_node is not None and extra_node not in cluster:  # a node of its own, never merged
        cluster[extra_node] = n
        node_pix.add(extra_node)
    edges: list[_Edge] = []
    seen: set[tuple[tuple[int, int], tuple[int, int]]] = set()
    for p in sorted(node_pix):
        for q in adj[p]:
            if (p, q) in seen or (q in cluster and cluster[q] == cluster[p]):
                continue
            chain = [p, q]
            prev, cur = p, q
            while cur not in cluster:
                nxt = [s for s in adj[cur] if s != prev]
                if not nxt:  # cannot happen for a degree-2 pixel; guard against malformed input
                    break
                prev, cur = cur, nxt[0]
                chain.append(cur)
            if cur not in cluster:
                continue
            seen.add((p, q))
            seen.add((chain[-1], chain[-2]))
            steps = np.diff(np.asarray(chain, dtype=np.float64), axis=0)
            edges.append(_Edge(cluster[p], cluster[cur], chain, float(np.linalg.norm(steps, axis=1).sum())))
    return cluster, edges


def _degrees(n_nodes: int, edges: Sequence[_Edge]) -> np.ndarray:
    deg = np.zeros(n_nodes, dtype=np.int64)
    for e in edges:
        deg[e.u] += 1
        deg[e.v] += 1
    return deg


def _prune(skel: np.ndarray, min_length: float, rounds: int = 10) -> np.ndarray:
    """Remove terminal branches (endpoint to junction) shorter than ``min_length`` px, repeatedly."""
    skel = skel.copy()
    for _ in range(rounds):
        adj = _adjacency(skel)
        cluster, edges = _graph(adj)
        if not cluster:
            break
        deg = _degrees(max(cluster.values()) + 1, edges)
        cut = False
        for e in edges:
            ends = (deg[e.u], deg[e.v])
            if e.length < min_length and min(ends) == 1 and max(ends) >= 3:
                tip = e.u if deg[e.u] == 1 else e.v
                for p in e.chain:
                    if p not in cluster or cluster[p] == tip:
                        skel[p] = False
                cut = True
        if not cut:
            break
    return skel


def _merge_junctions(
    cluster: dict[tuple[int, int], int], edges: list[_Edge], min_length: float
) -> tuple[dict[tuple[int, int], int], list[_Edge]]:
    """One node for junctions joined by a branch shorter than ``min_length`` px (a crossing that skeletonisation
    split into two 3-way junctions); the joining branch is dropped."""
    if not cluster:
        return cluster, edges
    n = max(cluster.values()) + 1
    deg = _degrees(n, edges)
    parent = list(range(n))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    keep = []
    for e in edges:
        if e.u != e.v and deg[e.u] >= 3 and deg[e.v] >= 3 and e.length < min_length and root(e.u) != root(e.v):
            parent[root(e.u)] = root(e.v)
        else:
            keep.append(e)
    roots = sorted({root(a) for a in range(n)})
    new_id = {r: i for i, r in enumerate(roots)}
    relabel = [new_id[root(a)] for a in range(n)]
    return ({p: relabel[k] for p, k in cluster.items()},
            [_Edge(relabel[e.u], relabel[e.v], e.chain, e.length) for e in keep])  # fmt: skip


# ============================================================================================== longest trail
def _tangent(chain: list[tuple[int, int]], span: int) -> np.ndarray:
    """Unit (row, col) direction leaving chain[0] along the chain (over ``span`` pixels)."""
    a = np.asarray(chain[0], dtype=np.float64)
    b = np.asarray(chain[min(span, len(chain) - 1)], dtype=np.float64)
    d = b - a
    n = float(np.linalg.norm(d))
    return d / n if n > 0 else d


def _longest_trail(
    edges: Sequence[_Edge],
    starts: Sequence[int],
    *,
    turn_weight: float,
    height_weight: float,
    excursions: int,
    node_height: Sequence[float],
    span: int,
    max_expansions: int = 200_000,
) -> list[tuple[int, int]]:
    """Best trail [(edge, mode)] from one of ``starts`` by exhaustive DFS (``max_expansions`` bounds the work).

    Modes: 1 forward (u -> v), -1 backward, 0 an excursion out along a dead-end edge and back (a sharp return).
    Score: covered length - turn_weight * turning (rad, pi at an excursion's tip) + height_weight * |height of the
    end - height of the start| (writing runs top to bottom). Lengths and heights in the same pixel units.
    """
    deg = _degrees(len(node_height), edges)
    incident: dict[int, list[tuple[int, int]]] = {}
    out_dir: dict[tuple[int, int], np.ndarray] = {}
    in_dir: dict[tuple[int, int], np.ndarray] = {}
    for k, e in enumerate(edges):
        t_u, t_v = _tangent(e.chain, span), _tangent(e.chain[::-1], span)
        incident.setdefault(e.u, []).append((k, 1))
        incident.setdefault(e.v, []).append((k, -1))
        out_dir[(k, 1)], in_dir[(k, 1)] = t_u, -t_v
        out_dir[(k, -1)], in_dir[(k, -1)] = t_v, -t_u
        if e.u != e.v and min(deg[e.u], deg[e.v]) == 1 and max(deg[e.u], deg[e.v]) >= 3:
            base = e.u if deg[e.u] >= 3 else e.v
            out = t_u if base == e.u else t_v
            incident[base].append((k, 0))
            out_dir[(k, 0)], in_dir[(k, 0)] = out, -out
    best: list = [-math.inf, []]
    budget = [max_expansions]

    def dfs(node: int, used: int, left: int, arriving: np.ndarray | None, score: float, path: list, h0: float) -> None:
        total = score + height_weight * abs(node_height[node] - h0)
        if total > best[0] + 1e-9:
            best[0], best[1] = total, list(path)
        if budget[0] <= 0:
            return
        budget[0] -= 1
        for k, mode in incident.get(node, []):
            if used >> k & 1 or (mode == 0 and left == 0):
                continue
            e = edges[k]
            turn = 0.0 if arriving is None else math.acos(max(-1.0, min(1.0, float(arriving @ out_dir[(k, mode)]))))
            if mode == 0:
                nxt, turn = node, turn + math.pi
            else:
                nxt = e.v if mode == 1 else e.u
            path.append((k, mode))
            dfs(nxt, used | (1 << k), left - (mode == 0), in_dir[(k, mode)], score + e.length - turn_weight * turn,
                path, h0)  # fmt: skip
            path.pop()

    for s in starts:
        dfs(s, 0, excursions, None, 0.0, [], node_height[s])
    return best[1]


# ============================================================================================== strokes
@dataclass(frozen=True)
class Stroke:
    """The pen path of one digit image, in image pixels.

    Attributes:
        path: (P, 2) float64 ordered (x, y) points, x = column to the right, y = row upwards (y = H - 1 - row),
            original-image pixels, roughly 0.25 px apart; the last point is the attractor.
        closed: the skeleton had no endpoint (a closed loop, cut open by ``loop_gap``).
        n_endpoints: endpoints of the pruned skeleton.
        n_junctions: junction clusters of the pruned skeleton.
        coverage: trail length / total skeleton length (1 = every branch drawn).
        ink_share: share of the image's ink in the component kept (< 1: the digit was written in pieces).
        length: path length, px.
    """

    path: np.ndarray
    closed: bool
    n_endpoints: int
    n_junctions: int
    coverage: float
    ink_share: float
    length: float


def _arc(p: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def _resample_arc(p: np.ndarray, n: int) -> np.ndarray:
    s = _arc(p)
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, p[:, j]) for j in range(p.shape[1])], axis=1)


def _binarise(image: np.ndarray, threshold: float, upsample: int, min_hole: float) -> tuple[np.ndarray, float]:
    """(ink mask of the largest 8-connected component on the upsampled grid, its share of all ink)."""
    img = image.astype(np.float64) / 255.0
    big = scipy.ndimage.zoom(img, upsample, order=1) if upsample > 1 else img
    ink = big >= threshold
    labels, n = scipy.ndimage.label(ink, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return ink, 0.0
    sizes = scipy.ndimage.sum_labels(ink, labels, index=np.arange(1, n + 1))
    share = float(sizes.max() / sizes.sum())
    ink = labels == (1 + int(np.argmax(sizes)))
    holes, nh = scipy.ndimage.label(~ink)  # 4-connected background
    if nh:
        border = set(np.unique(np.concatenate([holes[0], holes[-1], holes[:, 0], holes[:, -1]]))) - {0}
        areas = scipy.ndimage.sum_labels(np.ones_like(ink), holes, index=np.arange(1, nh + 1))
        for k in range(1, nh + 1):
            if k not in border and areas[k - 1] < min_hole * upsample**2:
                ink[holes == k] = True
    return ink, share


def extract_stroke(
    image: Tensor | np.ndarray,
    *,
    threshold: float = 0.5,
    upsample: int = 4,
    min_hole: float = 1.5,
    prune: float = 3.0,
    merge: float = 3.0,
    turn_weight: float = 1.0,
    height_weight: float = 0.1,
    excursions: int = 1,
    loop_gap: float = 0.1,
    level_tol: float = 3.0,
    smooth: float = 0.75,
) -> Stroke:
    """The pen path of one digit image (module docstring, steps 1-5).

    Args:
        image: (H, W) intensities, uint8 0..255 (float and integer images are taken as 0..255 too; a bool image is
            an ink mask, True = 255).
        threshold: ink threshold, fraction of 255 (0 < threshold < 1).
        upsample: bilinear upsampling factor before binarisation, in [1, 64] (cost: H W upsample^2 pixels, at most
            1e8).
        min_hole: holes smaller than this (px^2, original pixels) are filled; loops are larger.
        prune: terminal skeleton branches shorter than this (px) are removed as spurs.
        merge: junctions joined by a branch shorter than this (px) are one crossing.
        turn_weight: px of length one radian of turning at a junction costs (tie-break between equal trails).
        height_weight: px of length one px of height between the trail's start and end is worth (writing runs top
            to bottom; decides between trails of nearly equal length, e.g. the two ways to finish a 4).
        excursions: at most this many sharp returns: out along a dead-end branch and back (the stem of a 4 above
            its bar, the closing flick of a 9); one pays off when the branch is longer than its turning cost.
        loop_gap: fraction of a closed trail dropped at its end, so that start and attractor differ (0 <= gap < 1).
        level_tol: ends within this height difference (px) count as level; the left-most then starts.
        smooth: standard deviation of the Gaussian smoothing along the path, px (0 = none).

    Raises:
        InvalidArgumentError: an argument out of range (named), or an image that is not 2-D.
        TooFewSamplesError: no ink, or a skeleton too short to give a path (< 2 px).
    """
    img = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
    if img.ndim != 2 or min(img.shape) < 2:
        raise InvalidArgumentError(f"image must be a 2-D (H, W) array, got shape {tuple(img.shape)}")
    check_float(threshold, "threshold", low=0.0, high=1.0, low_open=True, high_open=True)
    if img.dtype.kind not in "fiub" or not np.isfinite(img).all():
        raise InvalidArgumentError(f"image must hold finite real numbers (0..255), got {img.dtype}")
    if img.dtype.kind == "b":  # an ink mask: True is full ink (255), False none
        img = img.astype(np.uint8) * np.uint8(255)
    check_int(upsample, "upsample", low=1, high=MAX_UPSAMPLE)
    check_cost("upsample", float(img.shape[0] * img.shape[1]) * upsample**2, 1e8, "pixels after upsampling")
    if not 0.0 <= loop_gap < 1.0:
        raise InvalidArgumentError(f"loop_gap must lie in [0, 1), got {loop_gap}")
    check_int(excursions, "excursions", low=0, high=100)
    for name, value in (("min_hole", min_hole), ("prune", prune), ("merge", merge), ("turn_weight", turn_weight),
                        ("height_weight", height_weight), ("level_tol", level_tol), ("smooth", smooth)):  # fmt: skip
        if not (value >= 0 and math.isfinite(value)):
            raise InvalidArgumentError(f"{name} must be finite and >= 0, got {value}")
    try:
        from skimage.morphology import skeletonize
    except ImportError as exc:  # pragma: no cover - scikit-image is a dependency
        raise StoreError("stroke extraction needs scikit-image (pip install scikit-image)") from exc
    up = int(upsample)
    H, W = img.shape
    ink, ink_share = _binarise(img, threshold, up, min_hole)
    if not ink.any():
        raise TooFewSamplesError(f"the image has no ink at threshold {threshold}")
    skel = skeletonize(ink)
    skel = _prune(skel, prune * up)
    adj = _adjacency(skel)
    if len(adj) < 3:
        raise TooFewSamplesError(f"the skeleton has {len(adj)} pixels; a stroke needs at least 3")
    cluster, edges = _merge_junctions(*_graph(adj), merge * up)
    n_nodes = max(cluster.values()) + 1 if cluster else 0
    deg = _degrees(n_nodes, edges)
    endpoints = [k for k in range(n_nodes) if deg[k] == 1]
    n_junctions = int((deg >= 3).sum())
    closed = not endpoints
    if closed:  # start at the top-most (then left-most) pixel, made a node of its own
        top = min(adj, key=lambda p: (p[0], p[1]))
        cluster, edges = _merge_junctions(*_graph(adj, extra_node=top), merge * up)
        starts = [cluster[top]]
    else:
        starts = endpoints
    if not edges:
        raise TooFewSamplesError("the skeleton has no branch; a stroke needs at least 3 pixels")
    n_nodes = max(cluster.values()) + 1
    height = np.full(n_nodes, -np.inf)
    for p_, k_ in cluster.items():
        height[k_] = max(height[k_], -float(p_[0]))  # y up: minus the row (upsampled pixels)
    trail = _longest_trail(edges, starts, turn_weight=turn_weight * up, height_weight=height_weight,
                           excursions=int(excursions), node_height=height.tolist(), span=2 * up)  # fmt: skip
    deg = _degrees(n_nodes, edges)
    pix: list[tuple[int, int]] = []
    for k, mode in trail:
        e = edges[k]
        if mode == 1:
            chain = e.chain
        elif mode == -1:
            chain = e.chain[::-1]
        else:  # out from the junction to the dead end and back (a sharp return)
            out = e.chain if deg[e.u] >= 3 else e.chain[::-1]
            chain = out + out[-2::-1]
        pix.extend(chain if not pix or pix[-1] != chain[0] else chain[1:])
    rc = np.asarray(pix, dtype=np.float64)
    # upsampled grid -> original pixels (scipy.ndimage.zoom maps the corner samples onto each other)
    rows = rc[:, 0] * (H - 1) / (H * up - 1) if up > 1 else rc[:, 0]
    cols = rc[:, 1] * (W - 1) / (W * up - 1) if up > 1 else rc[:, 1]
    path = np.stack([cols, (H - 1) - rows], axis=1)
    total = sum(e.length for e in edges)
    coverage = sum(edges[k].length for k, _ in trail) / total if total > 0 else 1.0
    step = 0.25
    length = float(_arc(path)[-1])
    if length < 2 * step:
        raise TooFewSamplesError(f"the stroke is {length:.2f} px long; at least {2 * step} px are needed")
    dense = _resample_arc(path, max(3, int(math.ceil(length / step)) + 1))
    is_loop = closed and np.linalg.norm(dense[0] - dense[-1]) < 2.0
    if smooth > 0:
        sigma = smooth / (length / (dense.shape[0] - 1))
        mode = "wrap" if is_loop else "nearest"
        body = dense[:-1] if is_loop else dense
        body = scipy.ndimage.gaussian_filter1d(body, sigma, axis=0, mode=mode)
        dense = np.concatenate([body, body[:1]]) if is_loop else body
    if closed:
        lead = dense[min(len(dense) - 1, int(math.ceil(2.0 / step)))] - dense[0]
        # first move to the right: traverse the other way (counter-clockwise at the top); only a trail that comes
        # back to its start can be reversed without moving the start away from the top
        if is_loop and lead[0] > 0:
            dense = dense[::-1].copy()
        if is_loop and loop_gap > 0:
            s = _arc(dense)
            dense = dense[s <= (1.0 - loop_gap) * s[-1]]
    else:
        a, b = dense[0], dense[-1]
        if abs(a[1] - b[1]) > level_tol:
            flip = b[1] > a[1]
        else:
            flip = b[0] < a[0]
        if flip:
            dense = dense[::-1].copy()
    if dense.shape[0] < 3:
        raise TooFewSamplesError(f"the stroke has {dense.shape[0]} points after cutting its loop; at least 3")
    dense.setflags(write=False)
    return Stroke(dense, bool(closed), len(endpoints), n_junctions, float(coverage), float(ink_share),
                  float(_arc(dense)[-1]))  # fmt: skip


# ============================================================================================== demonstrations
def stroke_trajectory(
    path: np.ndarray,
    *,
    n_points: int = 200,
    mm_per_pixel: float = 2.25,
    mean_speed: float = 30.0,
    time_law: str = "min_jerk",
    cusp_angle: float | None = 120.0,
    cusp_window: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions (n, 2) mm, times (n,) s, velocities (n, 2) mm/s) of a pen path traversed in time.

    Positions are ``mm_per_pixel * (path - path[-1])``: the path ends at the origin. Duration T = length /
    ``mean_speed``. ``time_law``: ``min_jerk`` (s(t) = L (10 u^3 - 15 u^4 + 6 u^5), u = t / T: at rest at both ends)
    or ``constant`` (uniform speed, also through a cusp).

    With ``min_jerk``, the pen also comes to rest at every *cusp* of the path, where it reverses (the stem of a 4
    drawn up and back down): the path is cut there and each piece gets a minimum-jerk movement of its own, of
    duration piece length / ``mean_speed`` (the same T in all). One movement over a reversal would turn the
    velocity round at full speed: labels that no smooth motion through those positions has. A cusp is the point of
    sharpest turning in a stretch where the chords over ``cusp_window`` path units (px of the image) before and
    after a point turn by more than ``cusp_angle`` degrees; ``cusp_angle=None`` leaves the path in one movement.
    Why 120 degrees at 1 px: on the first 40 images of every digit of the MNIST test set (the default extraction),
    the turning maxima at that window are either below 90 degrees (corners, rounded by skeleton and smoothing) or
    above 170 (sharp returns), nothing between.

    Args:
        path: (n, 2) pen positions, px (``extract_stroke``'s ``Stroke.path``), finite, n >= 2 and not all at one
            point; consecutive duplicates are dropped.
        n_points: >= 3 samples at equal time steps.
        mm_per_pixel, mean_speed: finite numbers > 0 (mm per px, mm/s).
        cusp_angle: degrees in (0, 180), or None; cusp_window: > 0, path units.
    """
    if time_law not in ("min_jerk", "constant"):
        raise UnknownNameError("time law", str(time_law), ("min_jerk", "constant"))
    check_int(n_points, "n_points", low=3, high=MAX_POINTS)
    mm_per_pixel = check_float(mm_per_pixel, "mm_per_pixel", low=0.0, low_open=True)
    mean_speed = check_float(mean_speed, "mean_speed", low=0.0, low_open=True)
    if cusp_angle is not None:
        check_float(cusp_angle, "cusp_angle", low=0.0, high=180.0, low_open=True, high_open=True)
    check_float(cusp_window, "cusp_window", low=0.0, low_open=True)
    raw = real_array(path, "path")
    if raw.ndim != 2 or raw.shape[1] != 2:
        raise ShapeMismatchError(f"path must have shape (n, 2) (pen positions, px), got {raw.shape}")
    if raw.shape[0] < 2:
        raise TooFewSamplesError(f"path has {raw.shape[0]} points; a pen path needs at least 2")
    if not np.isfinite(raw).all():
        raise NonFiniteError("path contains NaN or Inf")
    s_px = _arc(raw)
    p = (raw - raw[-1]) * mm_per_pixel
    s = s_px * mm_per_pixel
    L = float(s[-1])
    if L <= 0:
        raise TooFewSamplesError("the path has zero length")
    keep = np.concatenate([[True], np.diff(s) > 1e-12])
    raw, p, s, s_px = raw[keep], p[keep], s[keep], s_px[keep]
    T = L / mean_speed
    u = np.linspace(0.0, 1.0, int(n_points))
    t = u * T
    if time_law == "min_jerk":
        cusps = [] if cusp_angle is None else _cusps(raw, s_px, float(cusp_angle), float(cusp_window))
        breaks = np.array([0.0, *(c * mm_per_pixel for c in cusps), L])  # arc length (mm) of each rest
        t_breaks = breaks / mean_speed
        piece = np.clip(np.searchsorted(t_breaks, t, side="right") - 1, 0, len(breaks) - 2)
        width = np.diff(t_breaks)[piece]
        v = np.clip((t - t_breaks[piece]) / width, 0.0, 1.0)  # time within each piece's movement, in [0, 1]
        q = breaks[piece] + (v**3 * (10 - 15 * v + 6 * v**2)) * np.diff(breaks)[piece]
        rate = 30 * v**2 * (1 - v) ** 2 * mean_speed  # ds/dt, mm/s (each piece's length / duration = mean_speed)
    else:
        q, rate = u * L, np.full_like(u, L / T)
    tangent = np.gradient(p, s, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    pos = np.stack([np.interp(q, s, p[:, j]) for j in range(2)], axis=1)
    tan = np.stack([np.interp(q, s, tangent[:, j]) for j in range(2)], axis=1)
    tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
    pos[-1] = 0.0
    return pos, t, tan * rate[:, None]


def _cusps(path: np.ndarray, s: np.ndarray, angle: float, window: float) -> list[float]:
    """Arc positions (path units, increasing) of the cusps of ``path`` (n, 2) with arc lengths ``s`` (n,): per
    stretch of points whose chords over ``window`` before and after turn by more than ``angle`` degrees, the point
    where the chords differ most (the second difference; on an exact reversal the turn is 180 degrees all along a
    stretch of 2 ``window``, the second difference peaks at its apex). Points within ``window`` of either end are
    excluded."""
    inner = (s >= window) & (s <= s[-1] - window)
    if not inner.any():
        return []
    at = s[inner]
    point = lambda z: np.stack([np.interp(z, s, path[:, j]) for j in range(2)], axis=1)  # noqa: E731
    here = point(at)
    before, after = here - point(at - window), point(at + window) - here
    cos = (before * after).sum(1) / np.maximum(np.linalg.norm(before, axis=1) * np.linalg.norm(after, axis=1), 1e-300)
    turn = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    sharp = np.concatenate([[False], turn > angle, [False]])
    starts = np.flatnonzero(sharp[1:] & ~sharp[:-1])
    ends = np.flatnonzero(~sharp[1:] & sharp[:-1])  # exclusive
    bend = np.linalg.norm(after - before, axis=1)  # the apex of a reversal: the largest second difference
    return [float(at[a + int(np.argmax(bend[a:b]))]) for a, b in zip(starts, ends)]


def _pair_distances(paths: list[np.ndarray]) -> tuple[Tensor, Tensor]:
    """(n, n) DTW distances between the paths centred on their boxes (64 points each): as given, and with the
    second one reversed."""
    from lfd_torch.metrics import dtw_distance

    n = len(paths)
    q = []
    for p in paths:
        r = _resample_arc(p, 64)
        lo, hi = r.min(0), r.max(0)
        q.append(r - 0.5 * (lo + hi))
    fwd = torch.tensor(np.stack(q))
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    i, j = i.reshape(-1), j.reshape(-1)
    return dtw_distance(fwd[i], fwd[j]).view(n, n), dtw_distance(fwd[i], fwd.flip(1)[j]).view(n, n)


def _medoid_orientation(paths: list[np.ndarray], flippable: Sequence[bool]) -> list[bool]:
    """Flip flags making the ``flippable`` paths agree in direction with the set's medoid; the others keep theirs."""
    n = len(paths)
    if n < 2:
        return [False] * n
    d_same, d_flip = _pair_distances(paths)
    ref = int(torch.minimum(d_same, d_flip).sum(1).argmin())
    return [bool(flippable[k] and d_flip[ref, k] < d_same[ref, k]) for k in range(n)]


def _alike(paths: list[np.ndarray], n: int) -> list[int]:
    """Indices (sorted) of the n paths most alike: the one whose n - 1 nearest (DTW) are nearest, and those."""
    if len(paths) <= n:
        return list(range(len(paths)))
    d, _ = _pair_distances(paths)
    near = d.sort(dim=1).values[:, 1:n].sum(1)  # column 0 is the path itself
    m = int(near.argmin())
    return sorted(d[m].argsort()[:n].tolist())


def mnist_demos(
    digit: int,
    n_demos: int = 3,
    *,
    directory: str | os.PathLike[str] | None = None,
    split: str = "test",
    offset: int = 0,
    indices: Sequence[int] | None = None,
    n_points: int = 200,
    mm_per_pixel: float = 2.25,
    mean_speed: float = 30.0,
    time_law: str = "min_jerk",
    cusp_angle: float | None = 120.0,
    cusp_window: float = 1.0,
    min_coverage: float = 0.8,
    min_ink_share: float = 0.9,
    consistent: bool = True,
    pool: int | None = None,
    stroke: dict | None = None,
    dtype: torch.dtype | str = torch.float64,
    device: torch.device | str | None = None,
) -> Demos:
    """Demonstrations of one digit from MNIST images: (n_demos, n_points, 2) mm, all ending at the origin.

    Takes the images labelled ``digit`` in file order, skipping the first ``offset`` (or exactly ``indices``, image
    numbers in the split), extracts their strokes (:func:`extract_stroke` with the keyword arguments ``stroke``)
    and times them (:func:`stroke_trajectory`: ``time_law``, with a rest at every cusp by ``cusp_angle`` and
    ``cusp_window``). Images whose stroke cannot be extracted, covers less than
    ``min_coverage`` of its skeleton (a digit the trail cannot draw in one go), or keeps less than
    ``min_ink_share`` of the ink (a digit written in pieces) are skipped and logged. With ``pool``, the first
    ``pool`` usable images are read and the ``n_demos`` most alike kept (the one whose ``n_demos - 1`` nearest
    strokes under DTW are nearest, and those), so that a set does not mix ways of writing a digit. Names are
    ``mnist/<split>/<image number>``.

    Raises:
        InvalidArgumentError: ``digit`` not in 0..9, ``n_demos`` < 1, ``offset`` < 0, ``pool`` < 1,
            ``min_coverage`` or ``min_ink_share`` outside [0, 1], an index that is not an integer, out of range or
            of another digit, or fewer usable images than ``n_demos``.
        UnknownNameError: a key of ``stroke`` that is not an :func:`extract_stroke` keyword (the message lists them).
        StoreError, UnknownNameError: from :func:`load_mnist`.
    """
    check_int(digit, "digit", low=0, high=9)
    check_int(n_demos, "n_demos", low=1, high=MAX_IMAGES)
    check_int(offset, "offset", low=0)
    check_int(pool, "pool", low=1, high=MAX_IMAGES, allow_none=True)
    check_int(n_points, "n_points", low=3, high=MAX_POINTS)
    check_float(mm_per_pixel, "mm_per_pixel", low=0.0, low_open=True)
    check_float(mean_speed, "mean_speed", low=0.0, low_open=True)
    if cusp_angle is not None:  # checked before any image is read, as stroke_trajectory checks them
        check_float(cusp_angle, "cusp_angle", low=0.0, high=180.0, low_open=True, high_open=True)
    check_float(cusp_window, "cusp_window", low=0.0, low_open=True)
    if stroke is not None and not isinstance(stroke, Mapping):
        raise InvalidArgumentError(f"stroke must be a mapping of extract_stroke keyword arguments, got {stroke!r}")
    stroke_keys = tuple(inspect.signature(extract_stroke).parameters)[1:]  # after the image
    for key in stroke or {}:
        if key not in stroke_keys:
            raise UnknownNameError("stroke keyword (extract_stroke argument)", str(key), stroke_keys)
    if indices is not None:
        if isinstance(indices, (str, bytes)) or not isinstance(indices, Iterable):
            raise InvalidArgumentError(f"indices must be a sequence of image numbers, got {indices!r}")
        if isinstance(indices, (np.ndarray, Tensor)):
            indices = indices.reshape(-1).tolist()  # int stays int, float and bool stay what they are (rejected)
        indices = [check_int(i, "indices", low=0) for i in indices]  # 0.5 must not become image 0
    for name, value in (("min_coverage", min_coverage), ("min_ink_share", min_ink_share)):
        if not 0.0 <= value <= 1.0:
            raise InvalidArgumentError(f"{name} must lie in [0, 1], got {value}")
    images, labels = load_mnist(split, directory)
    if indices is not None:
        candidates = [int(i) for i in indices]
        for i in candidates:
            if not 0 <= i < labels.shape[0]:
                raise InvalidArgumentError(f"indices: image {i} out of range 0..{labels.shape[0] - 1}")
            if int(labels[i]) != int(digit):
                raise InvalidArgumentError(f"indices: image {i} is a {int(labels[i])}, not a {int(digit)}")
    else:
        candidates = torch.nonzero(labels == int(digit)).reshape(-1)[int(offset) :].tolist()
    kw = dict(stroke or {})
    level_tol = float(kw.get("level_tol", inspect.signature(extract_stroke).parameters["level_tol"].default))
    paths, names, level = [], [], []
    want = max(int(n_demos), int(pool or 0))
    for i in candidates:
        if len(paths) == want:
            break
        try:
            st = extract_stroke(images[i], **kw)
        except TooFewSamplesError as exc:
            log.info("MNIST %s image %d (digit %d) skipped: %s", split, i, digit, exc)
            continue
        if st.coverage < min_coverage or st.ink_share < min_ink_share:
            log.info("MNIST %s image %d (digit %d) skipped: coverage %.2f (min %.2f), ink share %.2f (min %.2f)",
                     split, i, digit, st.coverage, min_coverage, st.ink_share, min_ink_share)  # fmt: skip
            continue
        paths.append(st.path)
        names.append(f"mnist/{split}/{i}")
        level.append(not st.closed and abs(float(st.path[0, 1] - st.path[-1, 1])) <= level_tol)
    if len(paths) < n_demos:
        raise InvalidArgumentError(
            f"n_demos: {n_demos} demonstrations of digit {digit} requested, only {len(paths)} usable images "
            f"among {len(candidates)} candidates of the {split} split"
        )
    if consistent:
        paths = [p[::-1].copy() if f else p for p, f in zip(paths, _medoid_orientation(paths, level))]
    if len(paths) > n_demos:
        keep = _alike(paths, int(n_demos))
        paths, names = [paths[k] for k in keep], [names[k] for k in keep]
    pos, times, vel = [], [], []
    for p in paths:
        x, t, v = stroke_trajectory(p, n_points=n_points, mm_per_pixel=mm_per_pixel, mean_speed=mean_speed,
                                    time_law=time_law, cusp_angle=cusp_angle, cusp_window=cusp_window)  # fmt: skip
        pos.append(x)
        times.append(t)
        vel.append(v)
    return Demos.from_sequences(
        pos, times=times, velocities=vel, attractor=np.zeros(2), names=names,
        dtype=resolve_dtype(dtype), device=resolve_device(device),
    )  # fmt: skip

