"""Numerical stability check of the engine's commanded field, every step and every modulation mode (eqs 19-21).

For step m with Lyapunov matrix P_m and attractor g_m, the engine commands u_m(x) = alpha(x) M(x) f_m(x)
(modulation, rate floor, speed cap). The check samples states in three regions,

* a box around the data: the bounding box of all training positions, grown by ``box_scale`` about its centre;
* near g_m: uniform in the ball of radius ``near_radius`` x span around g_m (where the radial floor and the c = 0
  rule matter);
* far away: at ``far_scale`` x span from the data centre in random directions,

evaluates u_m in each mode at each state, as a robot in step m, and records

    dV_m/dt = 2 (x - g_m)^T P_m u_m(x)      and the scale-free margin    cos = dV_m/dt / (2 ||P_m (x - g_m)|| ||u_m||),

the cosine between u_m and the gradient of V_m (-1 is a straight descent; a zero velocity away from g_m counts as
0, a stall). The field is certified numerically when every sampled dV_m/dt < 0; the report gives the worst margin
(largest cosine), the state, step and mode where it occurs, and the largest dV/dt. ``SkillLibrary.learn`` runs it
and stores the report in the manifest.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.modulation import MODULATION_MODES, Modulation
from lfd_torch.skills.arrival import Arrival

__all__ = ["MAX_FAR_SCALE", "StabilityReport", "check_stability", "stability_samples"]


@dataclass(frozen=True)
class StabilityReport:
    """Result of :func:`check_stability`.

    Attributes:
        passed: every sampled dV/dt < 0.
        worst_margin: largest cosine between u and grad V over all samples (< 0 when passed).
        worst_state: the state where it occurs (list of d floats).
        worst_step: its step; worst_mode: its mode; worst_region: ``box``, ``near`` or ``far``.
        max_dvdt: largest sampled dV/dt (units^2/s with P normalised as fitted).
        n_samples: states per step and mode.
        margins: ``{mode: [worst cosine of step 0, 1, ...]}``.
    """

    passed: bool
    worst_margin: float
    worst_state: list[float]
    worst_step: int
    worst_mode: str
    worst_region: str
    max_dvdt: float
    n_samples: int
    margins: dict[str, list[float]]

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


_SAMPLE_KWARGS = frozenset({"n_box", "n_near", "n_far", "box_scale", "near_radius", "far_scale"})

#: Largest ``far_scale`` (in spans of the data). The far region probes the field well outside the data (default 100
#: spans); larger scales add no new directions, they only bring the check's quadratic forms (Gaussian exponents,
#: (x - g)^T P (x - g), ||u||^2) towards overflow: far_scale = 1e300 gave inf / NaN margins and failed a stable
#: library. At 1e6 spans those squares are ~1e12 span^2 / sigma^2, far from overflow; the far states must also stay
#: below the dtype's overflow magnitude (:func:`~lfd_torch.utils.safe_magnitude`, checked with the library's dtype).
MAX_FAR_SCALE = 1e6


def stability_samples(
    library: Any,
    step: int,
    *,
    generator: torch.Generator,
    n_box: int = 2000,
    n_near: int = 500,
    n_far: int = 500,
    box_scale: float = 1.5,
    near_radius: float = 0.05,
    far_scale: float = 100.0,
) -> tuple[Tensor, Tensor]:
    """States (n, d) of the three regions for step m and their region codes (n,) (0 box, 1 near, 2 far).

    n = n_box + n_near + n_far <= 10^7 (the cost: one engine velocity evaluation per state, mode and step);
    far_scale <= :data:`MAX_FAR_SCALE`, with the far states below the overflow magnitude of the library's dtype
    (:func:`lfd_torch.utils.safe_magnitude`).
    """
    from lfd_torch.skills.library import SkillLibrary
    from lfd_torch.utils import check_cost, check_float, check_generator, check_int, safe_magnitude

    if not isinstance(library, SkillLibrary):
        raise InvalidArgumentError(f"library must be a SkillLibrary, got {type(library).__name__}")
    check_int(step, "step", low=0, high=library.n_steps - 1)
    check_generator(generator)
    for name, n in (("n_box", n_box), ("n_near", n_near), ("n_far", n_far)):
        check_int(n, name, low=0, high=10**7)
    check_cost("n_box + n_near + n_far", float(n_box + n_near + n_far), 1e7, "stability samples")
    for name, v in (("box_scale", box_scale), ("near_radius", near_radius)):
        check_float(v, name, low=0.0)
    check_float(far_scale, "far_scale", low=0.0, high=MAX_FAR_SCALE)
    f = {"dtype": library.dtype, "device": library.device}
    x_all = torch.cat([s.train_positions for s in library.skills]).to(**f)
    lo, hi = x_all.amin(0), x_all.amax(0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo).clamp_min(1e-12 * library.span)
    reach = float(centre.abs().max()) + far_scale * library.span
    if reach > safe_magnitude(f["dtype"]):
        raise InvalidArgumentError(f"far_scale = {far_scale!r} puts the far states {reach:.3g} units out, above "
                                   f"{safe_magnitude(f['dtype']):.3g} where {f['dtype']} squares overflow")  # fmt: skip
    d = x_all.shape[-1]
    g = library.skills[step].attractor.to(**f)
    gen_dev = generator.device

    def rand(*shape: int) -> Tensor:
        return torch.rand(shape, generator=generator, dtype=f["dtype"], device=gen_dev).to(f["device"])

    def directions(n: int) -> Tensor:
        z = torch.randn((n, d), generator=generator, dtype=f["dtype"], device=gen_dev).to(f["device"])
        return z / torch.linalg.vector_norm(z, dim=-1, keepdim=True)

    box = centre + box_scale * half * (2 * rand(n_box, d) - 1)
    near = g + near_radius * library.span * rand(n_near, 1) ** (1.0 / d) * directions(n_near)
    far = centre + far_scale * library.span * directions(n_far)
    x = torch.cat([box, near, far])
    region = torch.cat([torch.full((n,), i, dtype=torch.long, device=f["device"]) for i, n in enumerate((n_box, n_near, n_far))])
    return x, region


def check_stability(
    library: Any,
    *,
    modes: Sequence[str] = MODULATION_MODES,
    arrival: Arrival | None = None,
    lambda_limit: float | None = None,
    radial_floor: float | None = None,
    seed: int = 0,
    **sample_kwargs: Any,
) -> StabilityReport:
    """Sample states and check dV_m/dt < 0 of the engine's field for every step and mode (module docstring).

    Args:
        library: a :class:`~lfd_torch.skills.SkillLibrary`.
        modes: modulation modes to check.
        arrival: the engine's arrival settings (default :class:`Arrival`).
        lambda_limit, radial_floor: modulation settings (default: :class:`~lfd_torch.modulation.Modulation`'s).
        seed: seed of the sample states.
        **sample_kwargs: region sizes and scales of :func:`stability_samples`.
    """
    from lfd_torch.skills.engine import SkillEngine

    from lfd_torch.skills.library import SkillLibrary
    from lfd_torch.utils import check_int

    if not isinstance(library, SkillLibrary):
        raise InvalidArgumentError(f"library must be a SkillLibrary, got {type(library).__name__}")
    if isinstance(modes, str) or not isinstance(modes, Sequence) or not modes:
        raise InvalidArgumentError(f"modes must be a non-empty sequence of modulation modes, got {modes!r}")
    check_int(seed, "seed", low=0)
    unknown = sorted(set(sample_kwargs) - _SAMPLE_KWARGS)
    if unknown:
        raise InvalidArgumentError(f"unknown stability_samples argument(s) {unknown}; accepted: {sorted(_SAMPLE_KWARGS)}")
    kw = {k: v for k, v in (("lambda_limit", lambda_limit), ("radial_floor", radial_floor)) if v is not None}
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    samples = [stability_samples(library, m, generator=gen, **sample_kwargs) for m in range(library.n_steps)]
    # dV/dt < 0 is checked away from g_m only: at least one such state per step
    away = [torch.linalg.vector_norm(x - library.skills[m].attractor, dim=-1) > 0 for m, (x, _) in enumerate(samples)]
    for m, ((_, region), valid) in enumerate(zip(samples, away)):
        if not bool(valid.any()):
            n_box, n_near, n_far = torch.bincount(region, minlength=3).tolist()
            radius = repr(sample_kwargs["near_radius"]) if "near_radius" in sample_kwargs else "default"
            got = f"n_box = {n_box}, n_near = {n_near}, near_radius = {radius}, n_far = {n_far}"
            raise InvalidArgumentError(f"no stability sample of step {m} lies away from its attractor ({got}): give "
                                       "n_box or n_far >= 1, or n_near >= 1 with near_radius > 0")  # fmt: skip
    margins: dict[str, list[float]] = {}
    worst = (-float("inf"), [], -1, "", "")
    max_dvdt = -float("inf")
    regions = ("box", "near", "far")
    for mode in modes:
        engine = SkillEngine(library, Modulation(mode=mode, **kw), arrival)
        margins[mode] = []
        for m, ((x, region), valid) in enumerate(zip(samples, away)):
            skill = library.skills[m]
            step = torch.full((x.shape[0],), m, dtype=torch.long, device=x.device)
            u, _ = engine.velocity(x, step, torch.zeros_like(step, dtype=torch.bool))
            e = x - skill.attractor
            Pe = e @ skill.primitive.P
            dvdt = 2 * (Pe * u).sum(-1)
            denom = 2 * torch.linalg.vector_norm(Pe, dim=-1) * torch.linalg.vector_norm(u, dim=-1)
            cos = torch.where(denom > 0, dvdt / denom.clamp_min(torch.finfo(x.dtype).tiny), torch.zeros_like(dvdt))
            cos = torch.where(valid, cos, torch.full_like(cos, -1.0))
            i = int(cos.argmax())
            margins[mode].append(float(cos[i]))
            max_dvdt = max(max_dvdt, float(dvdt[valid].max()))
            if float(cos[i]) > worst[0]:
                worst = (float(cos[i]), x[i].tolist(), m, mode, regions[int(region[i])])
    n = int(samples[0][0].shape[0])
    return StabilityReport(worst[0] < 0 and max_dvdt < 0, worst[0], worst[1], worst[2], worst[3], worst[4],
                           max_dvdt, n, margins)  # fmt: skip
