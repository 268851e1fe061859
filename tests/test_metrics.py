"""Metrics E1, E2, E3, DTWD and aggregation, each against an independent per-sample loop or a closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lfd_torch.metrics.dtw as dtw_module
from lfd_torch.errors import (
    InvalidArgumentError,
    NonFiniteError,
    ShapeMismatchError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.metrics import (
    aggregate,
    cosine_dissimilarity,
    dtw_distance,
    quadrilateral_areas,
    swept_area,
    velocity_error,
)
from conftest import requires_cuda

F64 = torch.float64

# ----------------------------------------------------------------------------------------- naive references
# Plain-Python loops over one trajectory (lists of floats), written from the definitions in NOTES.md sec. 5.


def _norm(v):
    return math.sqrt(sum(c * c for c in v))


def _sub(p, q):
    return [x - y for x, y in zip(p, q)]


def naive_velocity_error(pred, ref, kind):
    terms = [_norm(_sub(r, p)) for p, r in zip(pred, ref)]
    if kind == "rms":
        return math.sqrt(sum(e * e for e in terms) / len(terms))
    return sum(terms) / len(terms)


def naive_cosine(pred, ref, eps):
    total = 0.0
    for p, r in zip(pred, ref):
        npn, nr = _norm(p), _norm(r)
        if npn <= eps and nr <= eps:
            cos = 1.0
        elif npn <= eps or nr <= eps:
            cos = 0.0
        else:
            cos = max(-1.0, min(1.0, sum(x * y for x, y in zip(p, r)) / (npn * nr)))
        total += abs(1.0 - cos)
    return total / len(pred)


def naive_triangle_gram(p, q, r):
    u, v = _sub(q, p), _sub(r, p)
    uu = sum(x * x for x in u)
    vv = sum(x * x for x in v)
    uv = sum(x * y for x, y in zip(u, v))
    return 0.5 * math.sqrt(max(uu * vv - uv * uv, 0.0))


def _shoelace(poly):
    return 0.5 * abs(sum(poly[k][0] * poly[(k + 1) % len(poly)][1] - poly[(k + 1) % len(poly)][0] * poly[k][1]
                         for k in range(len(poly))))


def _proper_crossing(a, b, c, d):
    """The point where segments ab and cd cross in their interiors (parametric line intersection), else None."""
    r, s = _sub(b, a), _sub(d, c)
    den = r[0] * s[1] - r[1] * s[0]
    if den == 0.0:
        return None
    w = _sub(c, a)
    t = (w[0] * s[1] - w[1] * s[0]) / den
    u = (w[0] * r[1] - w[1] * r[0]) / den
    if 0.0 < t < 1.0 and 0.0 < u < 1.0:
        return [a[0] + t * r[0], a[1] + t * r[1]]
    return None


def naive_quad_area(p0, p1, p2, p3):
    if len(p0) == 2:  # enclosed region: split a bow-tie at the crossing of two opposite edges, add the lobes
        x = _proper_crossing(p0, p1, p2, p3)
        if x is not None:
            return _shoelace([p0, x, p3]) + _shoelace([x, p1, p2])
        x = _proper_crossing(p1, p2, p3, p0)
        if x is not None:
            return _shoelace([p0, p1, x]) + _shoelace([x, p2, p3])
        return _shoelace([p0, p1, p2, p3])
    return naive_triangle_gram(p0, p1, p2) + naive_triangle_gram(p0, p2, p3)


def naive_swept_area(x, x_ref, reduction):
    areas = [naive_quad_area(x_ref[t], x_ref[t + 1], x[t + 1], x[t]) for t in range(len(x) - 1)]
    return sum(areas) if reduction == "sum" else sum(areas) / len(areas)


def naive_dtw(a, b, squared):
    n, m = len(a), len(b)
    D = [[math.inf] * (m + 1) for _ in range(n + 1)]
    D[0][0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            c = sum((x - y) ** 2 for x, y in zip(a[i - 1], b[j - 1]))
            if not squared:
                c = math.sqrt(c)
            D[i][j] = c + min(D[i - 1][j], D[i][j - 1], D[i - 1][j - 1])
    return math.sqrt(D[n][m]) if squared else D[n][m]


def rows(x: torch.Tensor, n: int) -> list[list[float]]:
    return x[:n].tolist()


def random_walks(generator, B, T, d, dtype=F64):
    return torch.randn(B, T, d, generator=generator, dtype=dtype).cumsum(1)


LENGTHS = [11, 4, 7, 2, 9]


# ----------------------------------------------------------------------------------------- E1 velocity error
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("kind", ["mean_norm", "rms"])
def test_velocity_error_matches_loop(generator, d, kind):
    B, T = len(LENGTHS), max(LENGTHS)
    pred = torch.randn(B, T, d, generator=generator, dtype=F64)
    ref = torch.randn(B, T, d, generator=generator, dtype=F64)
    lengths = torch.tensor(LENGTHS)
    pred[1, 4:] = float("nan")  # padding may hold anything
    got = velocity_error(pred, ref, lengths=lengths, kind=kind)
    want = [naive_velocity_error(rows(pred[b], n), rows(ref[b], n), kind) for b, n in enumerate(LENGTHS)]
    want = torch.tensor(want, dtype=F64)
    assert got.shape == (B,) and got.dtype == F64
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_velocity_error_mask_general_and_properties(generator):
    B, T, d = 4, 10, 2
    pred = torch.randn(B, T, d, generator=generator, dtype=F64)
    ref = torch.randn(B, T, d, generator=generator, dtype=F64)
    mask = torch.rand(B, T, generator=generator) < 0.6
    mask[:, 0] = True
    got = velocity_error(pred, ref, mask)
    want = torch.tensor(
        [naive_velocity_error(pred[b][mask[b]].tolist(), ref[b][mask[b]].tolist(), "mean_norm") for b in range(B)],
        dtype=F64,
    )
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert (velocity_error(pred, ref, mask, kind="rms") >= got - 1e-12).all()
    assert torch.equal(velocity_error(ref, ref, mask), torch.zeros(B, dtype=F64))
    # a prefix mask and the matching lengths agree
    lengths = torch.tensor([10, 3, 6, 1])
    prefix = torch.arange(T) < lengths.unsqueeze(1)
    assert torch.equal(velocity_error(pred, ref, prefix), velocity_error(pred, ref, lengths=lengths))


# ----------------------------------------------------------------------------------------- E2 cosine
@pytest.mark.parametrize("d", [2, 3])
def test_cosine_dissimilarity_matches_loop(generator, d):
    B, T = len(LENGTHS), max(LENGTHS)
    pred = torch.randn(B, T, d, generator=generator, dtype=F64)
    ref = torch.randn(B, T, d, generator=generator, dtype=F64)
    pred[0, 2] = 0.0  # one zero velocity
    pred[2, 3] = 0.0  # both zero
    ref[2, 3] = 0.0
    ref[4, 1] = 1e-12  # below eps: counts as zero
    lengths = torch.tensor(LENGTHS)
    got = cosine_dissimilarity(pred, ref, lengths=lengths, eps=1e-9)
    want = [naive_cosine(rows(pred[b], n), rows(ref[b], n), 1e-9) for b, n in enumerate(LENGTHS)]
    want = torch.tensor(want, dtype=F64)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_cosine_dissimilarity_known_values_and_zero_convention():
    ref = torch.tensor([[1.0, 0.0]], dtype=F64).expand(6, 1, 2)
    pred = torch.tensor([[3.0, 0.0], [-2.0, 0.0], [0.0, 5.0], [0.0, 0.0], [1.0, 1.0], [1e-10, 0.0]], dtype=F64)
    pred = pred.unsqueeze(1)
    got = cosine_dissimilarity(pred, ref)
    want = torch.tensor([0.0, 2.0, 1.0, 1.0, 1.0 - math.sqrt(0.5), 1.0], dtype=F64)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-15)
    both_zero = torch.zeros(1, 3, 2, dtype=F64)
    assert torch.equal(cosine_dissimilarity(both_zero, both_zero), torch.zeros(1, dtype=F64))
    # eps = 0: any non-zero vector has a direction, and still no NaN
    tiny = torch.tensor([[[1e-150, 0.0]]], dtype=F64)
    assert torch.equal(cosine_dissimilarity(tiny, ref[:1], eps=0.0), torch.zeros(1, dtype=F64))
    # a norm that underflows to zero makes the vector count as zero, never a 0/0
    underflow = torch.tensor([[[1e-300, -1e-300]]], dtype=F64)
    for p, r in [(underflow, ref[:1]), (underflow, underflow), (both_zero[:, :1], underflow)]:
        assert torch.isfinite(cosine_dissimilarity(p, r, eps=0.0)).all()


# ----------------------------------------------------------------------------------------- E3 swept area
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_swept_area_matches_loop(generator, d, reduction):
    B, T = len(LENGTHS), max(LENGTHS)
    x_ref = random_walks(generator, B, T, d)
    x = x_ref + 0.3 * torch.randn(B, T, d, generator=generator, dtype=F64)
    x[3, 2:] = float("inf")  # padding
    lengths = torch.tensor(LENGTHS)
    got = swept_area(x, x_ref, lengths=lengths, reduction=reduction)
    want = [naive_swept_area(rows(x[b], n), rows(x_ref[b], n), reduction) for b, n in enumerate(LENGTHS)]
    want = torch.tensor(want, dtype=F64)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_swept_area_closed_forms():
    n, length, h = 11, 2.0, 0.25
    s = torch.linspace(0.0, length, n, dtype=F64)
    ref2 = torch.stack([s, torch.zeros_like(s)], -1).unsqueeze(0)
    # parallel offset segment: a rectangle of area length * h, split into n - 1 quadrilaterals
    offset = ref2 + torch.tensor([0.0, h], dtype=F64)
    torch.testing.assert_close(swept_area(offset, ref2, reduction="sum"), torch.tensor([length * h], dtype=F64))
    torch.testing.assert_close(swept_area(offset, ref2), torch.tensor([length * h / (n - 1)], dtype=F64))
    # linearly growing offset: a triangle of area length * h / 2
    ramp = ref2 + torch.stack([torch.zeros_like(s), h * s / length], -1)
    torch.testing.assert_close(swept_area(ramp, ref2, reduction="sum"), torch.tensor([length * h / 2], dtype=F64))
    # the same rectangle embedded in 3-D by a rotation keeps its area
    q, _ = torch.linalg.qr(torch.tensor([[0.3, -1.0, 0.2], [0.9, 0.4, -0.5], [0.1, 0.7, 1.1]], dtype=F64))
    pad = lambda p: torch.cat([p, torch.zeros_like(p[..., :1])], -1) @ q.T  # noqa: E731
    rotated = swept_area(pad(offset), pad(ref2), reduction="sum")
    torch.testing.assert_close(rotated, torch.tensor([length * h], dtype=F64))
    # a non-planar 3-D quadrilateral: two triangles of area sqrt(2)/2 each
    quad = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 1], [0, 1, 0]], dtype=F64)
    torch.testing.assert_close(quadrilateral_areas(*quad), torch.tensor(math.sqrt(2.0), dtype=F64))
    # 2-D bow-tie (connectors cross at (0.5, 0.5)): the two lobes of 0.25 add up, they do not cancel
    bowtie = torch.tensor([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=F64)
    torch.testing.assert_close(quadrilateral_areas(*bowtie), torch.tensor(0.5, dtype=F64))
    # ... while the d >= 3 two-triangle rule of the same planar bow-tie gives the two triangles' 1.0 (documented)
    torch.testing.assert_close(quadrilateral_areas(*pad(bowtie.unsqueeze(0)).squeeze(0)), torch.tensor(1.0, dtype=F64))
    # the reviewer's zig-zag: a rollout oscillating across its reference scores 0.5 per quadrilateral, not 0
    zig_ref = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]], dtype=F64)
    zig = torch.tensor([[[0.0, 1.0], [1.0, -1.0], [2.0, 1.0]]], dtype=F64)
    torch.testing.assert_close(swept_area(zig, zig_ref), torch.tensor([0.5], dtype=F64))
    torch.testing.assert_close(swept_area(zig, zig_ref, reduction="sum"), torch.tensor([1.0], dtype=F64))
    # ... at any scale: no product of two tiny corner areas underflows
    tiny = swept_area(zig * 1e-150, zig_ref * 1e-150)
    torch.testing.assert_close(tiny / 1e-300, torch.tensor([0.5], dtype=F64))
    # zero for a rollout on the reference
    assert torch.equal(swept_area(ref2, ref2), torch.zeros(1, dtype=F64))


def test_swept_area_thin_triangles_float32():
    # A rollout lagging along the reference line sweeps (almost) zero area. The minor (Lagrange) form keeps float32
    # close to the float64 area of the same float32 points (measured 1e-4 relative); the difference form
    # |u|^2 |v|^2 - (u.v)^2 leaves sqrt(rounding) noise, 27x the true value here.
    direction = torch.tensor([0.6, -0.48, 0.64], dtype=torch.float32)
    s = torch.linspace(0.0, 100.0, 50)
    ref = (s.unsqueeze(-1) * direction).unsqueeze(0)
    lag = ((s - 1.7).unsqueeze(-1) * direction).unsqueeze(0)
    got = swept_area(lag, ref, reduction="sum")
    exact = swept_area(lag.double(), ref.double(), reduction="sum")
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), exact, rtol=1e-2, atol=0)


def random_quads(generator, n):
    """(4, 3n, 2) float64 quadrilaterals (x_ref,t, x_ref,t+1, x_t+1, x_t): uniform vertices, rollouts crossing the
    reference segment, and mm-scale swept-like quadrilaterals offset far from the origin."""
    uniform = torch.rand(4, n, 2, generator=generator, dtype=F64) * 2 - 1
    ref0 = torch.randn(n, 2, generator=generator, dtype=F64)
    step = torch.randn(n, 2, generator=generator, dtype=F64)
    normal = torch.stack([-step[:, 1], step[:, 0]], -1)
    side = torch.rand(2, n, 1, generator=generator, dtype=F64)
    jitter = 0.3 * torch.randn(2, n, 2, generator=generator, dtype=F64)
    # rollout endpoints on opposite sides of the reference segment: a bow-tie or a concave/convex quadrilateral
    rollout1 = ref0 + step - side[1] * normal + jitter[1]
    crossing = torch.stack([ref0, ref0 + step, rollout1, ref0 + side[0] * normal + jitter[0]])
    swept = 500.0 + 30.0 * torch.randn(4, n, 2, generator=generator, dtype=F64).cumsum(0)
    return torch.cat([uniform, crossing, swept], 1)


def test_quadrilateral_areas_vs_shapely(generator):
    import shapely  # dev dependency: a missing install must fail, not skip
    quads = random_quads(generator, 2000)
    got = quadrilateral_areas(*quads)
    polygons = shapely.polygons(quads.permute(1, 0, 2).numpy())
    want = torch.from_numpy(shapely.area(shapely.make_valid(polygons)))  # make_valid splits a bow-tie into its lobes
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
    n_bowtie = int((~shapely.is_valid(polygons)).sum())
    assert n_bowtie > quads.shape[1] // 5  # many crossing quadrilaterals were checked, not only simple ones
    shoelace = 0.5 * (quads[2] - quads[0])[:, 0] * (quads[3] - quads[1])[:, 1]
    shoelace = (shoelace - 0.5 * (quads[2] - quads[0])[:, 1] * (quads[3] - quads[1])[:, 0]).abs()
    assert ((got - shoelace) > 1e-3 * got).sum() >= n_bowtie // 2  # the signed shoelace would have failed there


def test_quadrilateral_areas_matches_loop_and_float32(generator):
    quads = random_quads(generator, 300)
    got = quadrilateral_areas(*quads)
    want = torch.tensor([naive_quad_area(*quads[:, k].tolist()) for k in range(quads.shape[1])], dtype=F64)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
    got32 = quadrilateral_areas(*quads.float())
    assert got32.dtype == torch.float32
    torch.testing.assert_close(got32.double(), want, rtol=2e-3, atol=1e-4 * float(want.max()))


@requires_cuda
@pytest.mark.cuda
def test_quadrilateral_areas_cuda_matches_cpu(generator):
    quads = random_quads(generator, 500)
    for dtype in (F64, torch.float32):
        got = quadrilateral_areas(*quads.to(dtype).cuda())
        assert got.device.type == "cuda" and got.dtype == dtype
        torch.testing.assert_close(got.cpu(), quadrilateral_areas(*quads.to(dtype)))


def test_quadrilateral_areas_degenerate_2d():
    cases = [  # (p0, p1, p2, p3), exact area
        ([[0, 0], [0, 0], [0, 0], [0, 0]], 0.0),  # one point
        ([[0, 0], [1, 0], [3, 0], [2, 0]], 0.0),  # collinear
        ([[0, 0], [1, 0], [0, 0], [1, 0]], 0.0),  # collinear, rollout reversed over the reference
        ([[0, 0], [1, 0], [1, 0], [0, 0]], 0.0),  # rollout on the reference
        ([[0, 0], [1, 0], [1, 0], [0, 1]], 0.5),  # touching at a vertex: a triangle
        ([[0, 0], [0, 0], [1, 1], [0, 1]], 0.5),  # zero-length reference segment
        ([[0, 0], [0, 0], [0, 1], [0, 1]], 0.0),  # both segments of zero length
        ([[0, 0], [1, 0], [2, -1], [0, 1]], 0.5),  # rollout crosses the reference line through x_ref,t+1
        ([[0, 0], [2, 0], [2, -1], [0, 1]], 1.0),  # symmetric bow-tie, reference crossed at its midpoint
        ([[0, 0], [2, 0], [0, 1], [2, 1]], 1.0),  # connectors cross at (1, 0.5)
        ([[0, 0], [2, 0], [2, 0], [1, 0]], 0.0),  # collinear with a repeated vertex
        ([[0, 0], [2, 0], [1, 1], [1, -1]], 1.0),  # rollout crosses the reference at (1, 0): lobes 0.5 + 0.5
    ]
    quads = torch.tensor([q for q, _ in cases], dtype=F64).permute(1, 0, 2)
    for dtype in (F64, torch.float32):
        got = quadrilateral_areas(*quads.to(dtype))
        assert torch.isfinite(got).all()
        want = torch.tensor([naive_quad_area(*q) for q, _ in cases], dtype=F64)
        torch.testing.assert_close(got.double(), want, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(want, torch.tensor([a for _, a in cases], dtype=F64))


def test_quadrilateral_areas_3d_vs_2d_planar(generator):
    # The two-triangle rule of a planar quadrilateral embedded in 3-D is never below the 2-D region area, equals it
    # when the diagonal p0p2 is inside (convex; reflex vertex at p0 or p2) and exceeds it by twice the notch triangle
    # when the reflex vertex is p1 (documented in quadrilateral_areas).
    quads = random_quads(generator, 500)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=generator, dtype=F64))
    shift = torch.randn(3, generator=generator, dtype=F64)
    lifted = torch.cat([quads, torch.zeros_like(quads[..., :1])], -1) @ q.T + shift
    area2, area3 = quadrilateral_areas(*quads), quadrilateral_areas(*lifted)
    assert (area3 >= area2 * (1 - 1e-9) - 1e-12).all()
    p0, p1, p2, p3 = quads
    cross = lambda u, v: u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]  # noqa: E731
    t012, t023 = 0.5 * cross(p1 - p0, p2 - p0), 0.5 * cross(p2 - p0, p3 - p0)
    simple = (area2 - (t012 + t023).abs()).abs() <= 1e-9 * area2
    inside = simple & (t012 * t023 > 0)  # p1 and p3 on opposite sides of the diagonal p0p2
    torch.testing.assert_close(area3[inside], area2[inside], rtol=1e-9, atol=1e-12)
    notch = simple & (t012 * t023 < 0)
    extra = 2 * torch.minimum(t012.abs(), t023.abs())
    torch.testing.assert_close(area3[notch], area2[notch] + extra[notch], rtol=1e-9, atol=1e-12)
    assert inside.sum() > 100 and notch.sum() > 20


def test_swept_area_vs_shapely(generator):
    import shapely  # dev dependency: a missing install must fail, not skip
    B, T = 3, 20
    x_ref = random_walks(generator, B, T, 2)
    x = x_ref + 2.0 * torch.randn(B, T, 2, generator=generator, dtype=F64)  # crosses the reference often
    lengths = torch.tensor([20, 13, 7])
    got = swept_area(x, x_ref, lengths=lengths, reduction="sum")
    n_bowtie = 0
    for b, n in enumerate(lengths.tolist()):
        quads = torch.stack([x_ref[b, : n - 1], x_ref[b, 1:n], x[b, 1:n], x[b, : n - 1]], 1).numpy()
        polygons = shapely.polygons(quads)
        n_bowtie += int((~shapely.is_valid(polygons)).sum())
        assert float(got[b]) == pytest.approx(float(shapely.area(shapely.make_valid(polygons)).sum()), rel=1e-9)
    assert n_bowtie >= 5


# ----------------------------------------------------------------------------------------- DTW
@pytest.mark.parametrize("d", [1, 2, 3])
@pytest.mark.parametrize("squared", [False, True])
def test_dtw_matches_naive_dp(generator, d, squared):
    la = torch.tensor([13, 1, 7, 20, 5, 9])
    lb = torch.tensor([8, 6, 1, 17, 11, 9])
    a = random_walks(generator, len(la), 20, d)
    b = random_walks(generator, len(lb), 17, d)
    a[0, 13:] = float("nan")  # padding never enters
    got = dtw_distance(a, b, la, lb, squared_cost=squared)
    want = torch.tensor(
        [naive_dtw(rows(a[k], int(la[k])), rows(b[k], int(lb[k])), squared) for k in range(len(la))], dtype=F64
    )
    assert got.shape == (len(la),) and got.dtype == F64
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_dtw_properties(generator):
    a = random_walks(generator, 4, 15, 2)
    b = random_walks(generator, 4, 12, 2)
    assert torch.equal(dtw_distance(a, a), torch.zeros(4, dtype=F64))
    torch.testing.assert_close(dtw_distance(a, b), dtw_distance(b, a), rtol=1e-14, atol=0)
    # time-warped copy (each sample repeated) has distance zero
    assert torch.equal(dtw_distance(a, a.repeat_interleave(2, dim=1)), torch.zeros(4, dtype=F64))
    # Euclidean-cost DTW bounds the squared-cost one: sqrt(sum c^2) <= sum c along the optimal path
    assert (dtw_distance(a, b, squared_cost=True) <= dtw_distance(a, b) + 1e-12).all()


def test_dtw_chunked_cpu_path_matches_single_batch(generator, monkeypatch):
    B = 23
    la = torch.randint(1, 30, (B,), generator=generator)
    lb = torch.randint(1, 25, (B,), generator=generator)
    a = random_walks(generator, B, 30, 2)
    b = random_walks(generator, B, 25, 2)
    whole = dtw_distance(a, b, la, lb)
    monkeypatch.setattr(dtw_module, "_CPU_CELLS_PER_DIAGONAL", 1)  # chunks of 8 pairs, sorted by size
    chunked = dtw_distance(a, b, la, lb)
    torch.testing.assert_close(chunked, whole, rtol=1e-14, atol=0)
    want = torch.tensor([naive_dtw(rows(a[k], int(la[k])), rows(b[k], int(lb[k])), False) for k in range(B)], dtype=F64)
    torch.testing.assert_close(chunked, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("d", [1, 2])
def test_dtw_squared_equals_dtaidistance(generator, d):
    from dtaidistance import dtw, dtw_ndim  # dev dependency: a missing install must fail, not skip

    B = 8
    la = torch.randint(20, 120, (B,), generator=generator)
    lb = torch.randint(20, 120, (B,), generator=generator)
    a = random_walks(generator, B, 120, d)
    b = random_walks(generator, B, 120, d)
    got = dtw_distance(a, b, la, lb, squared_cost=True)
    want = []
    for k in range(B):
        x = a[k, : int(la[k])].numpy().copy()
        y = b[k, : int(lb[k])].numpy().copy()
        if d == 1:
            want.append(dtw.distance(x[:, 0], y[:, 0], use_c=True))
        else:
            want.append(dtw_ndim.distance(x, y, use_c=True))
    torch.testing.assert_close(got, torch.tensor(want, dtype=F64), rtol=1e-9, atol=1e-9)


# ----------------------------------------------------------------------------------------- aggregation
def test_aggregate_pools_terms(generator):
    B, T, d = len(LENGTHS), max(LENGTHS), 2
    pred = torch.randn(B, T, d, generator=generator, dtype=F64)
    ref = torch.randn(B, T, d, generator=generator, dtype=F64)
    lengths = torch.tensor(LENGTHS)
    mask = torch.arange(T) < lengths.unsqueeze(1)
    all_errors = torch.linalg.vector_norm(ref - pred, dim=-1)[mask]  # every (i, t) term of the set
    e1 = velocity_error(pred, ref, lengths=lengths)
    torch.testing.assert_close(aggregate(e1, lengths), all_errors.mean(), rtol=1e-12, atol=0)
    rms = velocity_error(pred, ref, lengths=lengths, kind="rms")
    pooled_rms = aggregate(rms, lengths, kind="rms")
    torch.testing.assert_close(pooled_rms, all_errors.square().mean().sqrt(), rtol=1e-12, atol=0)
    torch.testing.assert_close(aggregate(e1), e1.mean(), rtol=1e-14, atol=0)
    with pytest.raises(TooFewSamplesError):
        aggregate(e1, torch.zeros(B, dtype=torch.long))
    with pytest.raises(ShapeMismatchError):
        aggregate(e1, lengths[:2])
    with pytest.raises(UnknownNameError):
        aggregate(e1, kind="median")


# ----------------------------------------------------------------------------------------- dtype, device, errors
def test_float32_path_runs_and_agrees(generator):
    la = torch.tensor([30, 12, 25])
    a = random_walks(generator, 3, 30, 2)
    b = a + 0.2 * torch.randn(3, 30, 2, generator=generator, dtype=F64)
    v = torch.randn(3, 30, 2, generator=generator, dtype=F64)
    w = torch.randn(3, 30, 2, generator=generator, dtype=F64)
    calls = [
        lambda x, y, p, q: velocity_error(p, q, lengths=la),
        lambda x, y, p, q: velocity_error(p, q, lengths=la, kind="rms"),
        lambda x, y, p, q: cosine_dissimilarity(p, q, lengths=la),
        lambda x, y, p, q: swept_area(x, y, lengths=la),
        lambda x, y, p, q: dtw_distance(x, y, la, la),
        lambda x, y, p, q: dtw_distance(x, y, la, la, squared_cost=True),
    ]
    for f in calls:
        ref64 = f(a, b, v, w)
        got32 = f(a.float(), b.float(), v.float(), w.float())
        assert got32.dtype == torch.float32 and got32.shape == (3,)
        torch.testing.assert_close(got32.double(), ref64, rtol=1e-4, atol=1e-5)


@requires_cuda
@pytest.mark.cuda
def test_cuda_matches_cpu(generator):
    la = torch.tensor([30, 12, 25])
    a = random_walks(generator, 3, 30, 3)
    b = a + 0.2 * torch.randn(3, 30, 3, generator=generator, dtype=F64)
    for f in [
        lambda x, y: velocity_error(x, y, lengths=la.to(x.device)),
        lambda x, y: cosine_dissimilarity(x, y, lengths=la.to(x.device)),
        lambda x, y: swept_area(x, y, lengths=la.to(x.device)),
        lambda x, y: dtw_distance(x, y, la.to(x.device), la.to(x.device)),
    ]:
        got = f(a.cuda(), b.cuda())
        assert got.device.type == "cuda"
        torch.testing.assert_close(got.cpu(), f(a, b), rtol=1e-12, atol=1e-12)


def test_errors_on_bad_input():
    x = torch.zeros(2, 5, 2, dtype=F64)
    with pytest.raises(ShapeMismatchError):
        velocity_error(x, torch.zeros(2, 4, 2, dtype=F64))
    with pytest.raises(ShapeMismatchError):
        cosine_dissimilarity(x[0], x[0])
    with pytest.raises(ShapeMismatchError):
        swept_area(x[..., :1], x[..., :1])  # d = 1 has no area
    with pytest.raises(ShapeMismatchError):
        dtw_distance(x, torch.zeros(3, 5, 2, dtype=F64))
    with pytest.raises(ShapeMismatchError):
        dtw_distance(x, torch.zeros(2, 5, 3, dtype=F64))
    with pytest.raises(ShapeMismatchError):
        velocity_error(x, x, torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ShapeMismatchError):
        dtw_distance(x, x, torch.tensor([6, 5]))
    bad = x.clone()
    bad[1, 2, 0] = float("nan")
    for f in (velocity_error, cosine_dissimilarity, swept_area):
        with pytest.raises(NonFiniteError) as err:
            f(bad, x)
        assert err.value.demo_index == 1
    with pytest.raises(NonFiniteError):
        dtw_distance(x, bad.clone().fill_(float("inf")))
    # NaN in the padding is fine
    assert torch.isfinite(swept_area(bad, x, lengths=torch.tensor([5, 2]))).all()
    with pytest.raises(TooFewSamplesError) as err:
        swept_area(x, x, lengths=torch.tensor([5, 1]))
    assert err.value.demo_index == 1
    with pytest.raises(TooFewSamplesError):
        swept_area(x, x, torch.tensor([[True, False, True, False, True]] * 2))  # no consecutive pair
    with pytest.raises(TooFewSamplesError):
        velocity_error(x, x, lengths=torch.tensor([0, 5]))
    with pytest.raises(TooFewSamplesError):
        dtw_distance(x, x, torch.tensor([3, 0]))
    with pytest.raises(InvalidArgumentError):
        velocity_error(x, x, torch.ones(2, 5, dtype=torch.bool), lengths=torch.tensor([5, 5]))
    with pytest.raises(InvalidArgumentError):
        velocity_error(x, x, torch.ones(2, 5))  # float mask
    with pytest.raises(InvalidArgumentError):
        cosine_dissimilarity(x, x, eps=-1.0)
    with pytest.raises(UnknownNameError):
        velocity_error(x, x, kind="mse")
    with pytest.raises(UnknownNameError):
        swept_area(x, x, reduction="max")
