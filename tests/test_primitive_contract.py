"""Contract every stable primitive (LPVDS, SEDS) must satisfy: batching, dtype, device, certificate, save/load.

:class:`PrimitiveContract` holds the tests; each model family inherits it and provides a fitted ``model`` fixture
(class-scoped: fitted once per family) and the ``demos`` it was fitted to.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from conftest import requires_cuda
from lfd_torch.data import Demos, load_lasa
from lfd_torch.ds import LPVDS, SEDS, StablePrimitive, fit_lpvds, fit_seds, load_primitive, quadratic_lyapunov_derivative
from lfd_torch.gmm import PCGMMFitter
from lfd_torch.errors import CertificationError, ShapeMismatchError, StoreError
from lfd_torch.gmm import fit_em
from lfd_torch.rollout import rollout


def small_lasa(shape: str, demos: tuple[int, ...] = (0, 1), stride: int = 10) -> Demos:
    """A LASA motion with few demonstrations, every ``stride``-th sample (velocities as shipped)."""
    full = load_lasa(shape)[list(demos)]
    seqs = full.sequences()
    return Demos.from_sequences(
        [s[::stride] for s in seqs],
        times=[full.times[i, : len(s)][::stride] for i, s in enumerate(seqs)],
        velocities=[full.velocities[i, : len(s)][::stride] for i, s in enumerate(seqs)],
        attractor=full.attractor,
    )


def naive_field(model: StablePrimitive, x: np.ndarray) -> np.ndarray:
    """Reference f(x) by a loop over points and components with scipy densities (float64)."""
    gmm = model.gmm
    w = gmm.weights.double().numpy()
    mu = gmm.means.double().numpy()
    S = gmm.covariances.double().numpy()
    A = model.A.double().numpy()
    g = model.attractor.double().numpy()
    out = np.zeros_like(x)
    for n, xn in enumerate(x):
        dens = np.array([w[k] * multivariate_normal(mu[k], S[k]).pdf(xn) for k in range(len(w))])
        gamma = dens / dens.sum()
        out[n] = sum(gamma[k] * (A[k] @ (xn - g)) for k in range(len(w)))
    return out


class PrimitiveContract:
    """Base test class: subclasses provide the ``model`` and ``demos`` fixtures."""

    kind: type[StablePrimitive]

    def test_kind_and_certificate(self, model: StablePrimitive) -> None:
        assert isinstance(model, self.kind)
        cert = model.stability_certificate()
        assert cert.margins.shape == (model.n_components,)
        assert cert.margins.dtype == torch.float64
        assert cert.certified and cert.max_margin < 0
        assert math.isclose(cert.max_margin, float(cert.margins.max()))

    def test_matches_naive_loop(self, model: StablePrimitive, demos: Demos) -> None:
        x, _, _ = demos.samples()
        x = x[::7]
        ref = naive_field(model, x.numpy())
        torch.testing.assert_close(model(x), torch.from_numpy(ref), rtol=1e-9, atol=1e-9)

    def test_batch_shapes(self, model: StablePrimitive, demos: Demos, generator: torch.Generator) -> None:
        lo, hi = demos.positions.amin((0, 1)), demos.positions.amax((0, 1))
        x = lo + (hi - lo) * torch.rand(3, 5, 4, model.dim, generator=generator, dtype=torch.float64)
        out = model(x)
        assert out.shape == x.shape
        flat = model(x.reshape(-1, model.dim)).reshape(x.shape)
        torch.testing.assert_close(out, flat, rtol=0, atol=0)
        single = torch.stack([model(p) for p in x.reshape(-1, model.dim)]).reshape(x.shape)
        torch.testing.assert_close(out, single, rtol=1e-12, atol=1e-12)
        feature_major = x.reshape(-1, model.dim).T.contiguous().T  # the (N, d) view the rollout engine passes
        torch.testing.assert_close(model(feature_major), flat.reshape(-1, model.dim), rtol=0, atol=0)

    def test_zero_at_attractor(self, model: StablePrimitive) -> None:
        assert torch.equal(model(model.attractor), torch.zeros_like(model.attractor))

    def test_lyapunov_derivative_negative(self, model: StablePrimitive, demos: Demos, generator: torch.Generator) -> None:
        x, _, _ = demos.samples()
        lo, hi = demos.positions.amin((0, 1)), demos.positions.amax((0, 1))
        span = hi - lo
        rand = lo - span + 3 * span * torch.rand(2000, model.dim, generator=generator, dtype=torch.float64)
        pts = torch.cat([x, rand])
        pts = pts[(pts - model.attractor).norm(dim=-1) > 1e-6]
        v_dot = model.lyapunov_derivative(pts)
        assert (v_dot < 0).all()
        ref = quadratic_lyapunov_derivative(pts, model(pts), model.attractor, model.P)
        torch.testing.assert_close(v_dot, ref)
        # dV/dt = sum_k gamma_k e^T (A_k^T P + P A_k) e <= max margin * ||e||^2 (margins are eigenvalues)
        bound = model.stability_certificate().max_margin * (pts - model.attractor).pow(2).sum(-1)
        assert (v_dot <= bound + 1e-9 * bound.abs()).all()

    def test_float32(self, model: StablePrimitive, demos: Demos) -> None:
        x, _, _ = demos.samples()
        m32 = model.to(dtype=torch.float32)
        out = m32(x.float())
        assert out.dtype == torch.float32 and m32.A.dtype == torch.float32 and m32.gmm.dtype == torch.float32
        torch.testing.assert_close(out.double(), model(x), rtol=1e-4, atol=1e-3)
        with pytest.raises(ShapeMismatchError):
            model(x.float())
        with pytest.raises(ShapeMismatchError):
            model(torch.zeros(4, model.dim + 1, dtype=torch.float64))

    def test_save_load_roundtrip(self, model: StablePrimitive, demos: Demos, tmp_path) -> None:
        path = model.save(tmp_path / "sub" / "model.pt")
        assert path.is_file() and not list(path.parent.glob("*.tmp"))
        loaded = self.kind.load(path)
        generic = load_primitive(path)
        assert type(loaded) is self.kind and type(generic) is self.kind
        assert loaded.info == model.info
        for name in ("A", "attractor", "P", "velocity_covariances"):
            assert torch.equal(getattr(loaded, name), getattr(model, name))
        x0 = demos.start_points
        a = rollout(model, x0, 0.01, 300, attractor=model.attractor)
        b = rollout(loaded, x0, 0.01, 300, attractor=loaded.attractor)
        assert torch.equal(a.positions, b.positions) and torch.equal(a.lengths, b.lengths)
        f32 = self.kind.load(path, dtype=torch.float32)
        assert f32.dtype == torch.float32

    def test_load_rejects_wrong_kind_and_version(self, model: StablePrimitive, tmp_path) -> None:
        path = model.save(tmp_path / "m.pt")
        other = SEDS if self.kind is LPVDS else LPVDS
        with pytest.raises(StoreError):
            other.load(path)
        state = model.state_dict()
        state["schema_version"] = 999
        with pytest.raises(StoreError):
            StablePrimitive.from_state_dict(state)
        with pytest.raises(StoreError):
            StablePrimitive.load(tmp_path / "missing.pt")

    def test_tampered_file_is_not_certified(self, model: StablePrimitive) -> None:
        state = model.state_dict()
        state["A"] = -state["A"]  # unstable
        with pytest.raises(CertificationError):
            StablePrimitive.from_state_dict(state)
        with pytest.raises(CertificationError):
            self.kind(
                gmm=model.gmm,
                A=-model.A,
                attractor=model.attractor,
                P=model.P,
                velocity_covariances=model.velocity_covariances,
            )

    @requires_cuda
    @pytest.mark.cuda
    def test_cuda(self, model: StablePrimitive, demos: Demos) -> None:
        x, _, _ = demos.samples()
        m = model.to(device="cuda")
        torch.testing.assert_close(m(x.cuda()).cpu(), model(x))


@functools.lru_cache(maxsize=None)
def _fitted(kind: str) -> tuple[StablePrimitive, Demos]:
    demos = small_lasa("Sshape")
    generator = torch.Generator().manual_seed(7)
    if kind == "LPVDS":
        model = fit_lpvds(demos, gmm=functools.partial(fit_em, n_components=4), generator=generator)
    else:
        model = fit_seds(demos, n_components=3, max_iter=60, generator=generator)
    return model, demos


class TestLPVDSContract(PrimitiveContract):
    kind = LPVDS

    @pytest.fixture
    def model(self) -> StablePrimitive:
        return _fitted("LPVDS")[0]

    @pytest.fixture
    def demos(self) -> Demos:
        return _fitted("LPVDS")[1]


class TestSEDSContract(PrimitiveContract):
    kind = SEDS

    @pytest.fixture
    def model(self) -> StablePrimitive:
        return _fitted("SEDS")[0]

    @pytest.fixture
    def demos(self) -> Demos:
        return _fitted("SEDS")[1]


def test_saved_primitive_detects_a_flipped_bit_and_random_bytes(tmp_path) -> None:
    from lfd_torch.ds import load_primitive
    from lfd_torch.errors import StoreError
    from lfd_torch.store.checksum import payload_digest

    demos = load_lasa("Angle")[[0, 1]]
    model = fit_lpvds(demos, gmm=PCGMMFitter(), generator=torch.Generator().manual_seed(0))
    path = model.save(tmp_path / "m.pt")
    state = torch.load(path, weights_only=True)
    assert state["sha256"] == payload_digest(state)
    state["gmm"]["means"][0, 0] += 1e-9  # a change far below any shape or certificate check
    torch.save(state, tmp_path / "flipped.pt")
    with pytest.raises(StoreError, match="checksum"):
        load_primitive(tmp_path / "flipped.pt")
    (tmp_path / "random.pt").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(StoreError):
        load_primitive(tmp_path / "random.pt")
    again = load_primitive(path)
    assert torch.equal(again.A, model.A)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_primitive_refuses_non_finite_positions(bad) -> None:
    from lfd_torch.errors import NonFiniteError

    demos = load_lasa("Angle")[[0]]
    model = fit_lpvds(demos, gmm=PCGMMFitter(), generator=torch.Generator().manual_seed(0))
    x = demos.positions[0, :5].clone()
    x[2, 1] = bad
    for call in (model, model.component_velocities, model.lyapunov_derivative):
        with pytest.raises(NonFiniteError):
            call(x)
