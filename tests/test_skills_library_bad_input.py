"""Bad input to the skill library and its settings: a save over a library that fails midway, fitters and ``reuse``
that do not give step m a primitive with attractor g_m, library files that pass their checksums but do not fit
the segmentation, library fields that could be saved but not loaded back, and settings that learn would refuse.
Every library is the 2-demo L-task of test_skills, learned without the stability check (well under a second)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os

import pytest
import torch

from lfd_torch.errors import InvalidArgumentError, NonFiniteError, ShapeMismatchError, StoreError, UnknownNameError
from lfd_torch.segmentation import FixedSegmenter
from lfd_torch.segmentation.synthetic import multi_step_demos
from lfd_torch.skills import SkillLibrary, SkillSettings, default_fitter
from test_skills import _l_task

F64 = torch.float64


@pytest.fixture(scope="module")
def task() -> tuple:
    return _l_task()


@pytest.fixture(scope="module")
def lib(task) -> SkillLibrary:
    demos, seg = task
    return SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False)


@pytest.fixture(scope="module")
def other_lib() -> SkillLibrary:
    """Another library (other data, another switch) to save over ``lib``."""
    demos, _ = _l_task(seed=1)
    return SkillLibrary.learn(demos, FixedSegmenter([0.4])(demos), generator=torch.Generator().manual_seed(2),
                              check=False)  # fmt: skip


def _learn(task, **kwargs) -> SkillLibrary:
    demos, seg = task
    return SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False, **kwargs)


def _contents(root) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in root.iterdir()}


# ---------------------------------------------------------------------------------------------- save
def test_a_save_that_fails_while_moving_files_keeps_the_old_library(lib, other_lib, tmp_path, monkeypatch) -> None:
    """Property: saving over a library is one change. Whichever rename fails (os.replace / os.rename raising OSError
    at call k, for every k until the save gets through), the save raises StoreError, the folder holds exactly the
    bytes it held before (the old library, other files, no staging folder, nothing beside it) and loads as the old
    library; the save that gets through loads as the new one and keeps the other files."""
    root = tmp_path / "lib"
    lib.save(root)
    (root / "demos.pt").write_bytes(b"an experiment's own file")
    before = _contents(root)
    real_replace, real_rename = os.replace, os.rename
    for k in range(1, 100):
        calls = []

        def failing(real, src, dst, **kw):
            calls.append(src)
            if len(calls) == k:
                raise OSError(28, "No space left on device (injected)")
            return real(src, dst, **kw)

        with monkeypatch.context() as mp:
            mp.setattr(os, "replace", lambda s, d, **kw: failing(real_replace, s, d, **kw))
            mp.setattr(os, "rename", lambda s, d, **kw: failing(real_rename, s, d, **kw))
            try:
                other_lib.save(root)
            except StoreError:
                failed = True
            else:
                failed = False
        if not failed:
            break
        assert _contents(root) == before, k
        assert [p.name for p in tmp_path.iterdir()] == ["lib"], k
        assert torch.equal(SkillLibrary.load(root).attractors, lib.attractors), k
    n_files = lib.n_steps + 3  # segmentation, steps, skills.pt, manifest
    assert k > 2 * n_files  # every file was written, moved aside and moved in before the save got through
    assert torch.equal(SkillLibrary.load(root).attractors, other_lib.attractors)
    assert (root / "demos.pt").read_bytes() == before["demos.pt"]
    assert sorted(p.name for p in root.iterdir()) == sorted(before)


def test_an_interrupt_while_moving_files_keeps_the_old_library(lib, other_lib, tmp_path, monkeypatch) -> None:
    """Property: an exception other than OSError (here KeyboardInterrupt on the last rename, the manifest's)
    propagates unchanged, and the old library is put back byte for byte."""
    root = tmp_path / "lib"
    lib.save(root)
    before = _contents(root)
    real, fired = os.replace, []

    def interrupted(src, dst, **kw):
        if not fired and str(dst) == str(root / "manifest.json") and ".saving" in str(src):
            fired.append(src)
            raise KeyboardInterrupt
        return real(src, dst, **kw)

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        other_lib.save(root)
    monkeypatch.setattr(os, "replace", real)
    assert fired
    assert _contents(root) == before
    assert torch.equal(SkillLibrary.load(root).attractors, lib.attractors)


# ---------------------------------------------------------------------------------------------- learn
def test_a_fitted_primitive_must_have_the_attractor_of_its_step(task, lib) -> None:
    """Property: every fitted primitive is checked as a reused one is: its attractor is g_m (a fitter returning
    another step's primitive, attractor [0, 0], is refused naming the step)."""
    with pytest.raises(ShapeMismatchError, match="step 0.*g_0"):
        _learn(task, primitive=lambda p, g, generator: lib.skills[1].primitive)


def test_a_fitted_primitive_must_have_the_dimension_and_dtype_of_the_demonstrations(task) -> None:
    """Property: a fitted primitive of another dimension (3-D) or dtype (float32 for float64 demonstrations), or a
    fitter that returns no primitive, is refused with an error naming the step."""
    corners = torch.tensor([[-1.0, 1.0, 0.5], [-1.0, 0.0, 0.2], [0.0, 0.0, 0.0]], dtype=F64)
    d3 = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, waypoints=corners, samples_per_step=60,
                          timing_jitter=0.0, waypoint_jitter=0.01, noise=0.002).demos  # fmt: skip
    lib3 = SkillLibrary.learn(d3, FixedSegmenter([0.5])(d3), generator=torch.Generator().manual_seed(1), check=False)
    with pytest.raises(ShapeMismatchError, match="step 0.*dimension 3"):
        _learn(task, primitive=lambda p, g, generator: lib3.skills[0].primitive)
    fit = default_fitter()
    with pytest.raises(ShapeMismatchError, match="step 0.*float32"):
        _learn(task, primitive=lambda p, g, generator: fit(p, g, generator=generator).to(dtype=torch.float32))
    with pytest.raises(InvalidArgumentError, match="step 0.*NoneType"):
        _learn(task, primitive=lambda p, g, generator: None)


@pytest.mark.parametrize("reuse", ["key_7", "key_str", "key_bool", "list"])
def test_reuse_must_map_step_indices(task, lib, reuse) -> None:
    """Property: ``reuse`` is a mapping whose keys are step indices 0..M-1; another key (7, "0", True) is not
    silently ignored and a list is not a raw TypeError: InvalidArgumentError naming reuse."""
    value = {"key_7": {7: lib.skills[0]}, "key_str": {"0": lib.skills[0]}, "key_bool": {True: lib.skills[1]},
             "list": [lib.skills[0]]}[reuse]  # fmt: skip
    with pytest.raises(InvalidArgumentError, match="reuse"):
        _learn(task, reuse=value)


# ---------------------------------------------------------------------------------------------- load
def _as_schema_1(root, *, skills: dict | None = None, copy: tuple[str, str] | None = None,
                 manifest: dict | None = None) -> None:  # fmt: skip
    """Alter a saved library as a schema-1 manifest (no digest) allows: new ``skills.pt`` content, a step file copied
    over another, manifest entries changed; the checksums are recomputed."""
    if skills is not None:
        torch.save(skills, root / "skills.pt")
    if copy is not None:
        (root / copy[1]).write_bytes((root / copy[0]).read_bytes())
    man = json.loads((root / "manifest.json").read_text())
    man.pop("digest")
    man["schema_version"] = 1
    man["files"] = {name: hashlib.sha256((root / name).read_bytes()).hexdigest() for name in man["files"]}
    man.update(manifest or {})
    (root / "manifest.json").write_text(json.dumps(man))


def _skills_file(root) -> dict:
    return torch.load(root / "skills.pt", weights_only=True)


@pytest.mark.parametrize("damage", ["h2_short", "h2_list", "h2_nan", "positions_dim", "positions_missing",
                                    "speed_negative", "duration_nan"])  # fmt: skip
def test_a_skills_file_that_does_not_fit_the_segmentation_is_a_store_error(lib, tmp_path, damage) -> None:
    """Property: ``skills.pt`` is checked against the segmentation (one finite threshold, (N_m, d) training positions
    and a finite speed and duration >= 0 per step) even where the checksums match: StoreError naming skills.pt and
    the entry, not a raw IndexError / AttributeError or a library that loads."""
    root = tmp_path / "lib"
    lib.save(root)
    SkillLibrary.load(root)
    extra = _skills_file(root)
    entry = {"h2_short": "h2_ref", "h2_list": "h2_ref", "h2_nan": "h2_ref", "positions_dim": "train_positions",
             "positions_missing": "train_positions", "speed_negative": "speed", "duration_nan": "duration"}[damage]
    if damage == "h2_short":
        extra["h2_ref"] = extra["h2_ref"][:1]
    elif damage == "h2_list":
        extra["h2_ref"] = extra["h2_ref"].tolist()
    elif damage == "h2_nan":
        extra["h2_ref"][1] = math.nan
    elif damage == "positions_dim":
        extra["train_positions"][1] = extra["train_positions"][1][:, :1]
    elif damage == "positions_missing":
        extra["train_positions"] = extra["train_positions"][:1]
    elif damage == "speed_negative":
        extra["speed"][0] = -1.0
    else:
        extra["duration"][1] = math.nan
    _as_schema_1(root, skills=extra)
    with pytest.raises(StoreError, match=f"skills.pt.*{entry}"):
        SkillLibrary.load(root)


def test_a_step_file_of_another_step_is_a_store_error(lib, tmp_path) -> None:
    """Property: each step file holds a primitive whose attractor is g_m of the segmentation: step_0.pt replaced by
    step_1.pt (checksums recomputed) is a StoreError naming step_0.pt, not a library with attractors g_1, g_1."""
    root = tmp_path / "lib"
    lib.save(root)
    _as_schema_1(root, copy=("step_1.pt", "step_0.pt"))
    with pytest.raises(StoreError, match="step_0.pt.*g_0"):
        SkillLibrary.load(root)


@pytest.mark.parametrize("n_steps", [0, 1, "2"])
def test_a_step_count_other_than_the_segmentations_is_a_store_error(lib, tmp_path, n_steps) -> None:
    """Property: the manifest's n_steps is the segmentation's (an integer >= 1); n_steps = 0 with a dtype is not a raw
    IndexError, 1 is not a library that ignores a step, "2" is not read as 2."""
    root = tmp_path / "lib"
    lib.save(root)
    _as_schema_1(root, manifest={"n_steps": n_steps})
    with pytest.raises(StoreError, match="n_steps"):
        SkillLibrary.load(root, dtype=torch.float32)


# ---------------------------------------------------------------------------------------------- construction
@pytest.mark.parametrize("field,value", [("entropy_quantile", 5.0), ("entropy_quantile", math.nan),
                                         ("entropy_quantile", "1"), ("span", "1"),
                                         ("segmentation", "x"), ("skills", ("a", "b")), ("skills", "ab"),
                                         ("info", {"t": torch.tensor(1.0)}), ("info", [("a", 1)]),
                                         ("stability", {"worst": object()}), ("stability", "passed")])  # fmt: skip
def test_library_fields_are_validated_at_construction(lib, field, value) -> None:
    """Property: every field of a constructed library is one that save writes and load reads back (entropy quantile
    in [0, 1] or None, finite span > 0, a Segmentation, a tuple of Skill, JSON-serialisable mappings for info and
    stability): InvalidArgumentError naming the field, not a raw AttributeError/TypeError or a library that saves
    and then does not load."""
    with pytest.raises(InvalidArgumentError, match=field):
        dataclasses.replace(lib, **{field: value})


def test_a_skill_whose_primitive_is_not_g_m_is_refused(lib) -> None:
    """Property: skills[m]'s primitive has the attractor g_m of the segmentation (what load checks), and its values
    are those load accepts (a finite threshold)."""
    s0, s1 = lib.skills
    with pytest.raises(ShapeMismatchError, match="g_0"):
        dataclasses.replace(lib, skills=(dataclasses.replace(s0, primitive=s1.primitive), s1))
    with pytest.raises(NonFiniteError, match="h2_ref"):
        dataclasses.replace(lib, skills=(s0, dataclasses.replace(s1, h2_ref=torch.tensor(math.nan, dtype=F64))))


def test_save_refuses_info_that_is_not_json_before_writing(lib, tmp_path) -> None:
    """Property: info changed after construction (a mutable dict) to hold a tensor makes save raise
    InvalidArgumentError naming info before anything is written (no folder, no staging files), not a raw
    TypeError from json.dumps."""
    mine = dataclasses.replace(lib, info={"fitted_steps": [0, 1]})
    mine.info["t"] = torch.tensor(1.0)
    root = tmp_path / "lib"
    with pytest.raises(InvalidArgumentError, match="info"):
        mine.save(root)
    assert not root.exists()


# ---------------------------------------------------------------------------------------------- settings
@pytest.mark.parametrize("kwargs,error", [({"entropy_quantile": 5.0}, InvalidArgumentError),
                                          ({"entropy_quantile": math.nan}, InvalidArgumentError),
                                          ({"entropy_reference": "bogus"}, UnknownNameError),
                                          ({"check": "no"}, InvalidArgumentError),
                                          ({"check": [("n_box", 1)]}, InvalidArgumentError),
                                          ({"check": 2}, InvalidArgumentError),
                                          ({"check": None}, InvalidArgumentError)])  # fmt: skip
def test_settings_refuse_what_learn_refuses(kwargs, error) -> None:
    """Property: SkillSettings checks its learn arguments at construction as learn does (quantile in [0, 1] or None,
    a known entropy reference, check a bool (0/1) or a mapping) instead of turning any check into a bool."""
    with pytest.raises(error, match=next(iter(kwargs))):
        SkillSettings(**kwargs)

