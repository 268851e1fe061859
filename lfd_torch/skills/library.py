"""Skill library: one certified primitive per step of a segmentation (paper Sec. III-B/C, Table I).

A skill m holds the stable primitive learned on the pieces of step m (``Segmentation.split(end_at_attractor=True)``,
attractor g_m), the step's training positions, its typical demonstrated speed, and the entropy threshold H2(x_r)
of the small-scale modulation computed at fit time (NOTES sec. 4: by default the largest H2 over the step's
training states; a quantile, or the paper's literal x_r = g_m, by ``entropy_quantile``; with
``entropy_reference="reproduction"`` at least the largest H2 of the states the unmodulated engine visits when it
reproduces the training demonstrations: with one demonstration the position Gaussians are thin across the path, and
the reproduction itself, 0.3 mm off the data on LASA, exceeds the training-state maximum, so that the small-scale
branch would fire on the nominal motion and pull it off the path towards g_m). The subtask space A_m
stays in the segmentation (``Segmentation.log_density`` / ``other_log_density``), which the library carries.

Persistence: ``save(dir)`` writes ``segmentation.pt``, one ``step_{m}.pt`` per primitive, ``skills.pt`` (training
positions, thresholds) and last ``manifest.json`` (schema, step order, routes, thresholds, the stability report of
:mod:`~lfd_torch.skills.stability`, the SHA-256 of every file). The files are staged and replace those of a library
already there as one change, the manifest last, so a directory whose manifest is readable is complete. ``load(dir)``
checks the schema, every checksum and the files' content against the segmentation, and raises
:class:`~lfd_torch.errors.StoreError` naming the missing, truncated, foreign or inconsistent file.

Notation: M steps, d state dimension, N_m training samples of step m; positions in data units (LASA: mm).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from lfd_torch.data import Demos
from lfd_torch.ds import StablePrimitive, fit_lpvds, load_primitive
from lfd_torch.errors import InvalidArgumentError, LfdError, ShapeMismatchError, StoreError, UnknownNameError
from lfd_torch.modulation import reference_entropy
from lfd_torch.segmentation import Segmentation
from lfd_torch.store import atomic_save
from lfd_torch.utils import (
    FLOAT_DTYPES,
    check_choice,
    check_float,
    check_int,
    check_path,
    check_tensor,
    float_dtype,
    resolve_device,
)

__all__ = ["LIBRARY_SCHEMA", "Skill", "SkillLibrary", "default_fitter"]

LIBRARY_SCHEMA = 2  # 2: the manifest carries a digest of its own content; 1 (without it) is still read
_KIND = "lfd_torch.SkillLibrary"
_MANIFEST = "manifest.json"

#: The step's typical speed is this quantile of its demonstrated speeds (a step that starts or ends at rest has a
#: low median; the engine's speed cap is relative to the speed at which the step is actually performed).
SPEED_QUANTILE = 0.9

Fitter = Callable[..., StablePrimitive]


def default_fitter() -> Fitter:
    """P-QLF LPV-DS on a PC-GMM (the paper's primitive), called as ``fit(demos, attractor, generator=g)``."""
    from lfd_torch.gmm import PCGMMFitter

    return functools.partial(fit_lpvds, gmm=PCGMMFitter(), lyapunov="pqlf")


@dataclass(frozen=True, eq=False)
class Skill:
    """The primitive of one step.

    Attributes:
        step: step index m in the segmentation.
        primitive: certified primitive with attractor g_m.
        h2_ref: 0-d threshold H2(x_r) of the small-scale modulation.
        train_positions: (N_m, d) positions of the step's training samples (without the appended g_m).
        speed: typical demonstrated speed of the step (the :data:`SPEED_QUANTILE` quantile), units/s (reference of
            the engine's speed cap).
        duration: median duration of the step's pieces, s (time scale of the engine's convergence rate).
    """

    step: int
    primitive: StablePrimitive
    h2_ref: Tensor
    train_positions: Tensor
    speed: float
    duration: float

    @property
    def attractor(self) -> Tensor:
        """(d,) g_m."""
        return self.primitive.attractor


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _is_attractor(a: Tensor, g: Tensor) -> bool:
    """Whether a primitive's attractor ``a`` is g (to float32 rounding where either is float32)."""
    rtol = 1e-6 if a.dtype == g.dtype == torch.float64 else 1e-5
    return a.shape == g.shape and torch.allclose(a, g.to(a), rtol=rtol, atol=1e-9)


def _check_step_primitive(prim: StablePrimitive, g: Tensor, m: int, what: str, *, where: str = "the demonstrations",
                          same_dtype: bool = True) -> StablePrimitive:
    """``prim`` if it has the dimension of g and the attractor g = g_m (and, with ``same_dtype``, g's dtype and
    device); ShapeMismatchError naming ``what`` and where g comes from (``where``) otherwise."""
    if same_dtype and (prim.dtype != g.dtype or prim.device != g.device):
        raise ShapeMismatchError(f"{what} is {prim.dtype} on {prim.device}, {where} {g.dtype} on {g.device}")
    if prim.dim != g.shape[0]:
        raise ShapeMismatchError(f"{what} has dimension {prim.dim}, {where} {g.shape[0]}")
    if not _is_attractor(prim.attractor, g):
        raise ShapeMismatchError(f"{what}: its attractor {prim.attractor.tolist()} is not g_{m} = {g.tolist()}")
    return prim


def _check_skill(m: int, s: Skill, seg: Segmentation) -> None:
    """Skill m of a library on ``seg``: a StablePrimitive with the attractor g_m of the segmentation
    (:func:`_check_step_primitive`), and the values :func:`_check_skill_values` accepts.

    The error is tagged with the library file that holds the faulty part (``_library_file``: ``step_<m>.pt`` for
    the primitive, ``skills.pt`` for the values), so that :meth:`SkillLibrary.load` names it.

    Raises:
        InvalidArgumentError (ShapeMismatchError, NonFiniteError): naming the skill and the value.
    """
    try:
        if not isinstance(s.primitive, StablePrimitive):
            raise InvalidArgumentError(f"skill {m}: primitive must be a StablePrimitive, got "
                                       f"{type(s.primitive).__name__}")  # fmt: skip
        _check_step_primitive(s.primitive, seg.attractors[m], m, f"skill {m}: the primitive",
                              where="the segmentation", same_dtype=False)  # fmt: skip
    except LfdError as exc:
        exc._library_file = f"step_{m}.pt"  # type: ignore[attr-defined]
        raise
    try:
        _check_skill_values(m, s.h2_ref, s.train_positions, s.speed, s.duration, seg.dim)
    except LfdError as exc:
        exc._library_file = "skills.pt"  # type: ignore[attr-defined]
        raise


def _check_skill_values(m: int, h2_ref: Any, train_positions: Any, speed: Any, duration: Any, dim: int) -> None:
    """The values of skill m: a finite 0-d h2_ref, (N_m, d) finite train_positions, finite speed and duration >= 0.

    Raises:
        InvalidArgumentError (ShapeMismatchError, NonFiniteError): naming the value and the step.
    """
    check_tensor(h2_ref, f"h2_ref of step {m}", ndim=0, shape_hint="()")
    check_tensor(train_positions, f"train_positions of step {m}", ndim=2, last_dim=dim, shape_hint=f"(N_m, {dim})")
    check_float(speed, f"speed of step {m}", low=0.0)
    check_float(duration, f"duration of step {m}", low=0.0)


def _check_json(value: Any, name: str) -> None:
    """InvalidArgumentError naming ``name`` when ``value`` cannot be written into the JSON manifest."""
    try:
        json.dumps(value, sort_keys=True, allow_nan=True)
    except (TypeError, ValueError, RecursionError) as exc:
        raise InvalidArgumentError(f"{name} must be JSON-serialisable (it is written into the manifest): "
                                   f"{type(exc).__name__}: {exc}") from exc  # fmt: skip


def _step_pieces(pieces: Demos) -> tuple[Tensor, float, float]:
    """Training positions (without the appended attractor sample), typical speed and median duration (s) of one
    step's pieces."""
    keep = pieces.mask.clone()
    last = (pieces.lengths - 1).clamp_min(0)
    keep[torch.arange(pieces.n_demos, device=keep.device), last] = False  # the appended g_m
    x = pieces.positions[keep]
    speed = torch.linalg.vector_norm(pieces.velocities[keep], dim=-1)
    durations = pieces.times[torch.arange(pieces.n_demos, device=keep.device), last] - pieces.times[:, 0]
    return x, float(speed.quantile(SPEED_QUANTILE)) if speed.numel() else 0.0, float(durations.median())


@dataclass(frozen=True, eq=False)
class SkillLibrary:
    """Skills of a task, with the segmentation that defines their steps, routes and subtask spaces.

    Attributes:
        segmentation: the segmentation (steps, attractors g_m, routes, subtask spaces A_m); the engine executes
            its :attr:`~lfd_torch.segmentation.Segmentation.demonstrated_routes` (:attr:`routes`).
        skills: M skills in step order (``skills[m].step == m``).
        entropy_quantile: how the thresholds were chosen (quantile of H2 over the training states; None: x_r = g_m).
        span: largest coordinate range of the training positions (data units); tolerances of the engine scale
            with it.
        stability: the stability report stored at learn time (:func:`~lfd_torch.skills.check_stability`), or None.
        info: JSON-serialisable metadata (fit times, fitter name).
    """

    segmentation: Segmentation
    skills: tuple[Skill, ...]
    entropy_quantile: float | None = 1.0
    span: float = 1.0
    stability: dict[str, Any] | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Every field is checked here, so that whatever is constructed can be saved and loaded back.
        seg = self.segmentation
        if not isinstance(seg, Segmentation):
            raise InvalidArgumentError(f"segmentation must be a Segmentation, got {type(seg).__name__}")
        if not isinstance(self.skills, (tuple, list)):
            raise InvalidArgumentError(f"skills must be a tuple of Skill, got {type(self.skills).__name__}")
        for m, s in enumerate(self.skills):
            if not isinstance(s, Skill):
                raise InvalidArgumentError(f"skills must be a tuple of Skill, got a {type(s).__name__} at {m}")
        object.__setattr__(self, "skills", tuple(self.skills))
        M = seg.n_steps
        if len(self.skills) != M or any(s.step != m for m, s in enumerate(self.skills)):
            raise ShapeMismatchError(f"a library needs one skill per step in step order (0..{M - 1})")
        for m, s in enumerate(self.skills):
            _check_skill(m, s, seg)
        check_float(self.entropy_quantile, "entropy_quantile", low=0.0, high=1.0, allow_none=True)
        check_float(self.span, "span", low=0.0, low_open=True)
        if self.stability is not None and not isinstance(self.stability, Mapping):
            raise InvalidArgumentError(f"stability must be a mapping (a stability report) or None, got "
                                       f"{type(self.stability).__name__}")  # fmt: skip
        if not isinstance(self.info, Mapping):
            raise InvalidArgumentError(f"info must be a mapping, got {type(self.info).__name__}")
        _check_json(self.stability, "stability")
        _check_json(self.info, "info")

    # ------------------------------------------------------------------ properties
    @property
    def n_steps(self) -> int:
        return len(self.skills)

    @property
    def dim(self) -> int:
        return self.segmentation.dim

    @property
    def routes(self) -> tuple[tuple[int, ...], ...]:
        """The step orders the engine executes: :attr:`Segmentation.demonstrated_routes` (each one that a
        demonstration executed; a route whose demonstrations skip different steps gives several)."""
        return self.segmentation.demonstrated_routes

    @property
    def attractors(self) -> Tensor:
        """(M, d) g_m of the primitives."""
        return torch.stack([s.attractor for s in self.skills])

    @property
    def dtype(self) -> torch.dtype:
        return self.skills[0].primitive.dtype

    @property
    def device(self) -> torch.device:
        return self.skills[0].primitive.device

    # ------------------------------------------------------------------ learning
    @classmethod
    def learn(
        cls,
        demos: Demos,
        segmentation: Segmentation,
        *,
        primitive: Fitter | None = None,
        generator: torch.Generator,
        entropy_quantile: float | None = 1.0,
        entropy_reference: str = "training",
        reuse: Mapping[int, Skill | StablePrimitive] | None = None,
        check: Mapping[str, Any] | bool = True,
    ) -> SkillLibrary:
        """Fit one primitive per step on ``segmentation.split(demos, end_at_attractor=True)``.

        Args:
            demos: the demonstrations that were segmented.
            segmentation: their segmentation.
            primitive: fitter ``fit(demos_m, g_m, generator=g) -> StablePrimitive`` (default
                :func:`default_fitter`: P-QLF LPV-DS on a PC-GMM; SEDS, QLF or any other by config).
            generator: source of randomness for the fitter (one draw per step, in step order).
            entropy_quantile: threshold H2(x_r) = this quantile of H2 over the step's training states (1.0 = max);
                None: the paper's literal x_r = g_m.
            entropy_reference: ``training`` (the states above) or ``reproduction``: the threshold is also at least
                the largest H2 of the states that the unmodulated engine visits in each step when it reproduces the
                training demonstrations from their starts (module docstring).
            reuse: ``{m: skill or primitive}`` taken as the primitive of step m (a step index) instead of fitting one
                (a skill learned on another task); its attractor must equal g_m.
            check: run :func:`~lfd_torch.skills.check_stability` on the new library (True: default settings; a
                mapping: its keyword arguments; False: skip) and store the report.

        Returns:
            The library.

        Raises:
            InvalidArgumentError: ``reuse`` that is not a mapping of step indices; a fitter that does not return a
                StablePrimitive.
            ShapeMismatchError: demonstrations that are not the segmented ones; a reused or fitted primitive of
                another dimension or attractor (a fitted one also of another dtype or device).
            LfdError: whatever the fitter raises (SolverError, CertificationError, ...), with the step named.
        """
        if not isinstance(demos, Demos):
            raise InvalidArgumentError(f"demos must be a lfd_torch.data.Demos, got {type(demos).__name__}")
        if not isinstance(segmentation, Segmentation):
            raise InvalidArgumentError(f"segmentation must be a Segmentation, got {type(segmentation).__name__}")
        check_float(entropy_quantile, "entropy_quantile", low=0.0, high=1.0, allow_none=True)
        check_choice(entropy_reference, "entropy_reference", ("training", "reproduction"))
        if not isinstance(check, (bool, Mapping)):
            raise InvalidArgumentError(f"check must be a bool or a mapping of check_stability arguments, got {check!r}")
        if not isinstance(generator, torch.Generator):
            raise InvalidArgumentError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        fit = default_fitter() if primitive is None else primitive
        if not callable(fit):
            raise InvalidArgumentError(f"primitive must be a fitter callable, got {type(fit).__name__}")
        if reuse is None:
            reuse = {}
        if not isinstance(reuse, Mapping):
            raise InvalidArgumentError(f"reuse must be a mapping {{step index: skill or primitive}}, got "
                                       f"{type(reuse).__name__}")  # fmt: skip
        reuse = {check_int(k, "reuse key (a step index)", low=0, high=segmentation.n_steps - 1): v
                 for k, v in reuse.items()}  # fmt: skip
        pieces = segmentation.split(demos, end_at_attractor=True)
        skills = []
        fitted: list[int] = []
        for m, part in enumerate(pieces):
            g = segmentation.attractors[m].to(demos.positions)
            if m in reuse:
                prim = reuse[m].primitive if isinstance(reuse[m], Skill) else reuse[m]
                if not isinstance(prim, StablePrimitive):
                    raise InvalidArgumentError(f"reuse[{m}] is a {type(prim).__name__}, not a primitive or skill")
                prim = _check_step_primitive(prim.to(dtype=demos.dtype, device=demos.device), g, m, f"reuse[{m}]")
            else:
                try:
                    prim = fit(part, g, generator=generator)
                except LfdError as exc:
                    if _simple_init(exc):
                        raise type(exc)(f"step {m}: {exc}") from exc
                    raise
                if not isinstance(prim, StablePrimitive):
                    raise InvalidArgumentError(f"step {m}: the fitter (primitive=) returned a {type(prim).__name__}, "
                                               "not a StablePrimitive")  # fmt: skip
                _check_step_primitive(prim, g, m, f"step {m}: the fitted primitive")
                fitted.append(m)
            x_m, speed, duration = _step_pieces(part)
            h2 = reference_entropy(prim, x_m, entropy_quantile)
            skills.append(Skill(m, prim, h2.detach(), x_m.detach(), speed, duration))
        x_all = demos.samples()[0]
        span = float((x_all.amax(0) - x_all.amin(0)).max())
        lib = cls(segmentation, tuple(skills), entropy_quantile, span, None,
                  {"fitted_steps": fitted, "entropy_reference": entropy_reference})  # fmt: skip
        if entropy_reference == "reproduction":
            lib = _with_reproduction_thresholds(lib, demos)
        elif entropy_reference != "training":
            raise UnknownNameError("entropy reference", str(entropy_reference), ("training", "reproduction"))
        if check:
            from lfd_torch.skills.stability import check_stability

            report = check_stability(lib, **(dict(check) if isinstance(check, Mapping) else {}))
            lib = dataclasses.replace(lib, stability=report.to_dict())
        return lib

    def with_step(self, m: int, primitive: StablePrimitive) -> SkillLibrary:
        """A new library whose step m uses ``primitive`` (attractor g_m); the other skills are shared, not refitted.

        The threshold H2(x_r) of step m is recomputed for the new primitive; the stored stability report is
        dropped (run :func:`~lfd_torch.skills.check_stability` again).
        """
        if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < self.n_steps:
            raise InvalidArgumentError(f"m must be a step index in 0..{self.n_steps - 1}, got {m!r}")
        if not isinstance(primitive, StablePrimitive):
            raise InvalidArgumentError(f"primitive must be a StablePrimitive, got {type(primitive).__name__}")
        old = self.skills[m]
        prim = _check_step_primitive(primitive.to(dtype=self.dtype, device=self.device), old.attractor, m,
                                     "the primitive", where="the library", same_dtype=False)  # fmt: skip
        h2 = reference_entropy(prim, old.train_positions, self.entropy_quantile)
        skills = list(self.skills)
        skills[m] = Skill(m, prim, h2.detach(), old.train_positions, old.speed, old.duration)
        return dataclasses.replace(self, skills=tuple(skills), stability=None)

    # ------------------------------------------------------------------ persistence
    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Write the library into ``directory`` (module docstring); returns the manifest path.

        Every file is first written into a hidden staging folder inside ``directory``, then moved into place by
        renames, the manifest last, after the files of the same names already there were moved aside
        (:func:`_install`): a save that fails or is interrupted at any point leaves a library already there as it
        was (other files in ``directory`` are kept).

        Raises:
            StoreError: ``directory`` is not a usable folder, or writing or moving a file failed.
            InvalidArgumentError: ``info`` or ``stability`` is not JSON-serialisable (nothing is written).
        """
        root = check_path(directory, "directory", error=StoreError)
        _check_json(self.stability, "stability")  # mutable dicts: they may have changed since construction
        _check_json(self.info, "info")
        stage = root / f".saving-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            root.mkdir(parents=True, exist_ok=True)
            stage.mkdir()
        except OSError as exc:  # a file where the directory should be, no permission
            raise StoreError(f"cannot write the library into directory {root}: {exc}") from exc
        try:
            manifest = self._write_files(stage)
            _install(stage, root, [*manifest["files"], _MANIFEST])
        finally:
            shutil.rmtree(stage, ignore_errors=True)
        return root / _MANIFEST

    def _write_files(self, root: Path) -> dict[str, Any]:
        """Every file of the library and its manifest into ``root``; returns the manifest."""
        files: dict[str, str] = {}

        def put(name: str, obj: Any) -> None:
            atomic_save(root / name, lambda tmp: torch.save(obj, tmp), what="library file")
            files[name] = _sha256(root / name)

        self.segmentation.save(root / "segmentation.pt")
        files["segmentation.pt"] = _sha256(root / "segmentation.pt")
        for s in self.skills:
            s.primitive.save(root / f"step_{s.step}.pt")
            files[f"step_{s.step}.pt"] = _sha256(root / f"step_{s.step}.pt")
        put("skills.pt", {
            "h2_ref": torch.stack([s.h2_ref.cpu() for s in self.skills]),
            "train_positions": [s.train_positions.cpu() for s in self.skills],
            "speed": torch.tensor([s.speed for s in self.skills], dtype=torch.float64),
            "duration": torch.tensor([s.duration for s in self.skills], dtype=torch.float64),
        })  # fmt: skip
        manifest = {
            "kind": _KIND,
            "schema_version": LIBRARY_SCHEMA,
            "n_steps": self.n_steps,
            "dim": self.dim,
            "steps": [{"step": s.step, "file": f"step_{s.step}.pt", "kind": s.primitive.kind,
                       "attractor": s.attractor.tolist(), "h2_ref": float(s.h2_ref), "speed": s.speed,
                       "duration": s.duration}
                      for s in self.skills],  # fmt: skip
            "routes": [list(r) for r in self.routes],
            "entropy_quantile": self.entropy_quantile,
            "span": self.span,
            "stability": self.stability,
            "info": self.info,
            "files": files,
        }
        manifest["digest"] = _manifest_digest(manifest)
        text = json.dumps(manifest, indent=2, sort_keys=True, allow_nan=True)
        atomic_save(root / _MANIFEST, lambda tmp: tmp.write_text(text), what="library manifest")
        return manifest

    @classmethod
    def load(
        cls,
        directory: str | os.PathLike[str],
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> SkillLibrary:
        """Read a library written by :meth:`save`; every file is checked against its manifest checksum, and the
        manifest against its own digest (libraries of schema 1, written before the manifest had one, are read
        without that check). The content is then checked against the segmentation: one step file per step whose
        attractor is g_m, and thresholds, training positions, speeds and durations of the right shapes and values.

        Raises:
            StoreError: a missing, truncated, altered, foreign or inconsistent file (the message names it and the
                entry), or another schema.
            InvalidArgumentError, UnknownNameError: a bad ``dtype`` or ``device``.
        """
        dtype, device = float_dtype(dtype), resolve_device(device)  # the arguments' faults are not the files'
        root = check_path(directory, "directory", error=StoreError)
        man_path = root / _MANIFEST
        try:
            manifest = json.loads(man_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise StoreError(f"cannot read the library manifest {man_path}: {exc}") from exc
        if not isinstance(manifest, dict) or manifest.get("kind") != _KIND:
            raise StoreError(f"{man_path} is not a skill-library manifest")
        schema = manifest.get("schema_version")
        if schema not in (1, LIBRARY_SCHEMA):
            raise StoreError(f"{man_path}: schema {schema!r}, expected {LIBRARY_SCHEMA} (or 1)")
        if schema != 1 and manifest.get("digest") != _manifest_digest(manifest):
            raise StoreError(f"{man_path} does not match its digest (edited or damaged)")
        try:
            files = dict(manifest["files"])
            n_steps = check_int(manifest["n_steps"], f"{man_path}: n_steps", low=1, error=StoreError)
            span = check_float(manifest["span"], f"{man_path}: span", low=0.0, low_open=True, error=StoreError)
            quantile = check_float(manifest.get("entropy_quantile"), f"{man_path}: entropy_quantile", low=0.0, high=1.0,
                                   allow_none=True, error=StoreError)
        except (KeyError, TypeError, ValueError) as exc:
            raise StoreError(f"{man_path}: a missing or bad entry ({type(exc).__name__}: {exc})") from exc
        for name, digest in files.items():
            path = root / name
            if not path.is_file():
                raise StoreError(f"library file {path} is missing")
            if _sha256(path) != digest:
                raise StoreError(f"library file {path} does not match its checksum (truncated or altered)")
        needed = ["segmentation.pt", "skills.pt"] + [f"step_{m}.pt" for m in range(n_steps)]
        for name in needed:
            if name not in files:
                raise StoreError(f"{man_path} does not list {name}")
        seg = Segmentation.load(root / "segmentation.pt")
        if seg.n_steps != n_steps:
            raise StoreError(f"{man_path}: n_steps is {n_steps}, the segmentation file has {seg.n_steps} steps")
        extra_path = root / "skills.pt"
        try:
            extra = torch.load(extra_path, map_location="cpu", weights_only=True)
            h2, xs, speed, duration = extra["h2_ref"], extra["train_positions"], extra["speed"], extra["duration"]
        except Exception as exc:
            raise StoreError(f"cannot read {extra_path}: {exc}") from exc
        try:
            for name, t in (("h2_ref", h2), ("speed", speed), ("duration", duration)):
                check_tensor(t, name, ndim=1, finite=False, shape_hint=f"({n_steps},)")
                if t.shape[0] != n_steps:
                    raise ShapeMismatchError(f"{name} has {t.shape[0]} entries for {n_steps} steps")
            if not isinstance(xs, (list, tuple)) or len(xs) != n_steps:
                got = f"{len(xs)} of them" if isinstance(xs, (list, tuple)) else f"a {type(xs).__name__}"
                raise ShapeMismatchError(f"train_positions must be a list of {n_steps} tensors, got {got}")
        except LfdError as exc:
            raise StoreError(f"library file {extra_path}: {exc}") from exc
        skills = []
        for m in range(n_steps):
            prim = load_primitive(root / f"step_{m}.pt", dtype=dtype, device=device)
            f = {"dtype": prim.dtype, "device": prim.device}
            x_m = xs[m].to(**f) if isinstance(xs[m], Tensor) and xs[m].dtype in FLOAT_DTYPES else xs[m]  # else refused
            skills.append(Skill(m, prim, h2[m].to(**f), x_m, float(speed[m]), float(duration[m])))
        if dtype is not None or device is not None:
            seg = _segmentation_to(seg, skills[0].primitive.dtype, skills[0].primitive.device)
        try:  # the constructor checks every skill against the segmentation (_check_skill names the faulty file)
            return cls(seg, tuple(skills), quantile, span, manifest.get("stability"),
                       dict(manifest.get("info") or {}))  # fmt: skip
        except (KeyError, TypeError, ValueError, LfdError) as exc:
            part = getattr(exc, "_library_file", None)
            if part is not None:
                raise StoreError(f"library file {root / part}: {exc}") from exc
            raise StoreError(f"{man_path}: inconsistent library ({exc})") from exc


def _install(stage: Path, root: Path, names: list[str]) -> None:
    """Move the files ``names`` (the manifest last) from ``stage`` into ``root`` as one change.

    The files of the same names already in ``root`` are first moved aside into a hidden folder, the manifest first
    (meanwhile ``root`` holds no library rather than a mixed one). If a move fails or an exception interrupts it,
    the new files are removed and the old ones put back.

    Raises:
        StoreError: a move failed (the old files are back), or putting them back failed too (the message names the
            folder that holds them).
    """
    aside = stage.with_name(stage.name + ".old")
    moved: list[str] = []
    placed: list[str] = []
    try:
        aside.mkdir()
        for name in [_MANIFEST, *(n for n in names if n != _MANIFEST)]:
            if os.path.lexists(root / name):
                os.replace(root / name, aside / name)
                moved.append(name)
        for name in names:
            os.replace(stage / name, root / name)
            placed.append(name)
    except BaseException as exc:
        for name in placed:
            with contextlib.suppress(OSError):
                os.unlink(root / name)
        lost = []
        for name in reversed(moved):  # the manifest last
            try:
                os.replace(aside / name, root / name)
            except OSError:
                lost.append(name)
        if lost:
            raise StoreError(f"cannot move the library files into {root} ({type(exc).__name__}: {exc}), nor put the "
                             f"previous files {lost} back: they are in {aside}") from exc  # fmt: skip
        shutil.rmtree(aside, ignore_errors=True)
        if isinstance(exc, OSError):
            raise StoreError(f"cannot move the library files into {root}: {exc}") from exc
        raise
    shutil.rmtree(aside, ignore_errors=True)


def _manifest_digest(manifest: dict) -> str:
    """SHA-256 of the manifest's content without its own ``digest`` entry, as JSON reads it back (keys become
    strings, tuples lists) with the keys sorted, so that the digest at save and at load see the same text."""
    body = json.loads(json.dumps({k: v for k, v in manifest.items() if k != "digest"}, allow_nan=True))
    return hashlib.sha256(json.dumps(body, sort_keys=True, allow_nan=True).encode()).hexdigest()


def _with_reproduction_thresholds(lib: SkillLibrary, demos: Demos, dt: float = 0.01) -> SkillLibrary:
    """Raise each threshold to the largest H2 on the unmodulated engine's reproduction of the training demos."""
    from lfd_torch.modulation import renyi_entropy
    from lfd_torch.skills.engine import SkillEngine

    engine = SkillEngine(lib, "none")
    horizon = float(demos.durations.max()) * 5.0 + 5.0
    out = engine.rollout(demos.start_points.to(lib.dtype), dt=dt, n_steps=max(1, int(horizon / dt)))
    x, steps, valid = out.result.positions, out.steps, out.result.mask
    skills = list(lib.skills)
    for m, s in enumerate(skills):
        sel = valid & (steps == m)
        if bool(sel.any()):
            h2 = renyi_entropy(s.primitive, x[sel]).max()
            skills[m] = dataclasses.replace(s, h2_ref=torch.maximum(s.h2_ref, h2.detach()))
    return dataclasses.replace(lib, skills=tuple(skills))


def _simple_init(exc: Exception) -> bool:
    """Whether ``type(exc)(message)`` rebuilds the error (errors with extra constructor arguments are re-raised)."""
    try:
        type(exc)("probe")
    except TypeError:
        return False
    return True


def _segmentation_to(seg: Segmentation, dtype: torch.dtype, device: torch.device) -> Segmentation:
    """The segmentation with its floating tensors in ``dtype`` on ``device``."""
    f = {"dtype": dtype, "device": device}
    return dataclasses.replace(
        seg,
        attractors=seg.attractors.to(**f),
        space_mean=seg.space_mean.to(**f),
        space_covariance=seg.space_covariance.to(**f),
        space_weights=seg.space_weights.to(**f),
        endpoints=None if seg.endpoints is None else seg.endpoints.to(**f),
    )
