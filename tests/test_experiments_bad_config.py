"""Bad configurations of the experiment scripts: each is refused with a typed error naming its key, before fitting.

Every script's ``run(cfg)`` is called on a composed configuration (as tests/test_experiments.py does). The checks of
values run at the top of ``run`` -- :func:`no_fitting` makes any fit an AssertionError, so a check that ran only
after fitting fails here -- and a configuration error raised inside a fit is raised, never stored as a failed row.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from lfd_torch.errors import (
    InvalidArgumentError,
    InvalidGMMError,
    SolverError,
    TooFewSamplesError,
    UnknownNameError,
)
from lfd_torch.store import prepare_job, read_table, write_table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))

BENCH = ["shapes=[Angle]", "segmentations=[none]", "primitives=[lpvds]", "modulations=[none]", "progress=false",
         "budget_s=2"]  # fmt: skip
PRIMITIVES = ["data.shape=Angle"]
TASKS = ["shapes=[Angle]", "segmentation=none", "n_random=2", "budget_s=2", "figures=false", "progress=false"]
MNIST = ["digits=[7]", "data.n_demos=2", "data.pool=null", "data.n_points=120", "data.directory={mnist}",
         "n_perturbed=1", "budget_s=15", "n_resample=40", "figures=false", "progress=false"]  # fmt: skip
SCOOP = ["segmentation=none", "starts.n=1", "n_disturbed=2", "budget_s=1", "figures=false", "render=false", "workers=1",
         "progress=false"]  # fmt: skip


def _compose(name: str, overrides: list[str], **kw) -> object:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(name, overrides=overrides, **kw)


def _refuse(*args, **kwargs):
    raise AssertionError("a model was fitted before the configuration was checked")


@pytest.fixture
def no_fitting(monkeypatch):
    """Every fit (skill library, scooping task, SEDS / LPV-DS primitive, segmentation) raises AssertionError."""
    import lfd_torch.ds
    import lfd_torch.segmentation
    import scooping
    from lfd_torch.skills import SkillLibrary

    monkeypatch.setattr(SkillLibrary, "learn", classmethod(_refuse))
    monkeypatch.setattr(scooping, "learn_scooping", _refuse)
    for name in ("fit_seds", "fit_lpvds"):
        monkeypatch.setattr(lfd_torch.ds, name, _refuse)
    monkeypatch.setattr(lfd_torch.segmentation, "segment", _refuse)


@pytest.fixture(scope="module")
def mnist_dir(tmp_path_factory) -> Path:
    """A tiny MNIST test set (two 7s, two 1s), as tests/test_figures.py writes it."""
    from test_mnist import one, seven, write_set

    folder = tmp_path_factory.mktemp("mnist")
    write_set(folder, np.stack([seven(), one(), seven(1.0), one(-1.0)]), np.array([7, 1, 7, 1], dtype=np.uint8),
              gz=False)  # fmt: skip
    return folder


# (script, overrides, error, pattern the message must match)
UPFRONT = [
    # defect 8: numbers and lists of lasa_benchmark
    ("lasa_benchmark", BENCH + ["dt=0"], InvalidArgumentError, r"^dt must be"),
    ("lasa_benchmark", BENCH + ["budget_s=nan"], InvalidArgumentError, r"^budget_s must be"),
    ("lasa_benchmark", BENCH + ["dt=abc"], InvalidArgumentError, r"^dt must be"),
    ("lasa_benchmark", BENCH + ["dt=-0.01"], InvalidArgumentError, r"^dt must be"),
    ("lasa_benchmark", BENCH + ["budget_s=0.001"], InvalidArgumentError, r"budget_s / dt"),
    ("lasa_benchmark", BENCH + ["segmentations=[]"], InvalidArgumentError, r"^segmentations must"),
    ("lasa_benchmark", BENCH + ["primitives=[lpvds,lpvds]"], InvalidArgumentError, r"^primitives names lpvds"),
    # defect 9: names that are not keys of cfg.fitters / cfg.segmenters (the message lists those)
    ("lasa_benchmark", BENCH + ["primitives=[lpvd]"], UnknownNameError, r"primitives 'lpvd'; valid names: seds, lpvds"),
    ("lasa_benchmark", BENCH + ["segmentations=[bp]"], UnknownNameError,
     r"segmentations 'bp'; valid names: bp_gm_hmm, none"),
    ("lasa_benchmark", BENCH + ["modulations=[ful]"], UnknownNameError, r"modulations 'ful'"),
    # defect 5: the modulation's entropy_quantile is not the threshold the engine uses
    ("lasa_benchmark", BENCH + ["modulations=[full]", "modulation.entropy_quantile=0.1"], InvalidArgumentError,
     r"^modulation.entropy_quantile=0.1 differs from skills.entropy_quantile"),
    ("lasa_tasks", TASKS + ["modulation.entropy_quantile=0.1"], InvalidArgumentError, r"^modulation.entropy_quantile"),
    ("mnist", MNIST + ["modulation.entropy_quantile=0.1"], InvalidArgumentError, r"^modulation.entropy_quantile"),
    ("scooping", SCOOP + ["modulation.entropy_quantile=0.1"], InvalidArgumentError, r"^modulation.entropy_quantile"),
    # defect 8: lasa_primitives
    ("lasa_primitives", PRIMITIVES + ["rollout.dt=0"], InvalidArgumentError, r"^rollout.dt must be"),
    ("lasa_primitives", PRIMITIVES + ["rollout.horizon_factor=nan"], InvalidArgumentError,
     r"^rollout.horizon_factor must be"),
    # defect 7: a typo in training is not "all"
    ("lasa_tasks", TASKS + ["training=[one,al]"], UnknownNameError, r"^unknown training 'al'; valid names: one, all$"),
    ("lasa_tasks", TASKS + ["training=[one,al]", "figures=true"], UnknownNameError, r"^unknown training 'al'"),
    ("lasa_tasks", TASKS + ["dt=0"], InvalidArgumentError, r"^dt must be"),
    # defect 8: mnist
    ("mnist", MNIST + ["dt=0"], InvalidArgumentError, r"^dt must be"),
    ("mnist", MNIST + ["budget_s=nan"], InvalidArgumentError, r"^budget_s must be"),
    ("mnist", MNIST + ["n_perturbed=-1"], InvalidArgumentError, r"^n_perturbed must be"),
    ("mnist", MNIST + ["reach_radius=-1"], InvalidArgumentError, r"^reach_radius must be"),
    # defect 8: scooping
    ("scooping", SCOOP + ["threads=0"], InvalidArgumentError, r"^threads must be"),
    ("scooping", SCOOP + ["batch_size=0"], InvalidArgumentError, r"^batch_size must be"),
    ("scooping", SCOOP + ["budget_s=-1"], InvalidArgumentError, r"^budget_s must be"),
    ("scooping", SCOOP + ["modes=[]"], InvalidArgumentError, r"^modes must"),
    # defects 8, 10: lasa_metrics
    ("lasa_metrics", ["shapes=[]"], InvalidArgumentError, r"^shapes must"),
    ("lasa_metrics", ["shapes=[Line]", "seed=abc"], InvalidArgumentError, r"^seed must be an integer"),
    ("lasa_metrics", ["shapes=[Line]", "plot_metric=area"], UnknownNameError, r"^unknown plot_metric 'area'"),
]


@pytest.mark.parametrize(("script", "overrides", "error", "pattern"), UPFRONT,
                         ids=[f"{s}:{o[-1]}" for s, o, _, _ in UPFRONT])  # fmt: skip
def test_bad_settings_raise_a_typed_error_naming_the_key_before_fitting(script, overrides, error, pattern, tmp_path,
                                                                         no_fitting, request):  # fmt: skip
    """Property: run(cfg) of a configuration with one bad setting raises ``error`` whose message names the key,
    before any model is fitted (no_fitting) and before any result is written."""
    module = __import__(script)
    if any("{mnist}" in o for o in overrides):
        overrides = [o.format(mnist=request.getfixturevalue("mnist_dir")) for o in overrides]
    cfg = _compose(script, overrides + [f"+out_dir={tmp_path}"])
    with pytest.raises(error, match=pattern):
        module.run(cfg)
    assert not list(tmp_path.rglob("*.parquet"))


def test_modulation_entropy_quantile_follows_the_skill_library_threshold():
    """Property: skills.entropy_quantile is the one H2 threshold; the experiments' modulation.entropy_quantile
    follows it (the sweep_modulation preset sweeps skills.entropy_quantile and stays accepted)."""
    import lasa_benchmark
    import lasa_tasks
    import mnist
    import scooping

    for name, module in (("lasa_benchmark", lasa_benchmark), ("lasa_tasks", lasa_tasks), ("mnist", mnist),
                         ("scooping", scooping)):  # fmt: skip
        cfg = _compose(name, ["skills.entropy_quantile=0.9"])
        assert cfg.modulation.entropy_quantile == 0.9, name
        module.check_config(cfg)
        assert _compose(name, []).modulation.entropy_quantile == 1.0, name  # the default is unchanged


def test_fit_errors_split_into_configuration_errors_and_failed_fits(tmp_path, monkeypatch):
    """Property: a genuine fit failure (solver, bad demonstration, invalid fitted mixture) is stored as a failed row,
    but a configuration error raised inside the fit (fitters.lpvds.eps=-1, segmenters.bp_gm_hmm.stickiness=-1) is
    raised, and no table is written."""
    import lasa_benchmark

    failures = iter([SolverError("solver status infeasible"), TooFewSamplesError("step 0 has 2 samples"),
                     InvalidGMMError("covariance 0 is not positive definite")])  # fmt: skip

    def failing(primitive_cfg):
        def fit(*args, **kwargs):
            raise next(failures)

        return fit

    with monkeypatch.context() as m:
        m.setattr(lasa_benchmark, "fitter", failing)
        cfg = _compose("lasa_benchmark", BENCH + ["modulations=[none,full]", "primitives=[lpvds,seds]",
                                                  f"+out_dir={tmp_path / 'fail'}"])  # fmt: skip
        table = lasa_benchmark.run(cfg)["table"]
        assert len(table) == 2 * 2 * 7 and (table.status != "ok").all()
        assert set(table.status.str.split(":").str[0]) == {"SolverError", "TooFewSamplesError"}
        table = lasa_benchmark.run(_compose("lasa_benchmark", BENCH + [f"+out_dir={tmp_path / 'gmm'}"]))["table"]
        assert len(table) == 7 and table.status.str.startswith("InvalidGMMError").all()
    for overrides, key in ((["fitters.lpvds.eps=-1"], "eps"),
                           (["segmentations=[bp_gm_hmm]", "segmenters.bp_gm_hmm.stickiness=-1"], "stickiness")):
        out = tmp_path / key
        cfg = _compose("lasa_benchmark", BENCH + overrides + [f"+out_dir={out}"])
        with pytest.raises(InvalidArgumentError, match=key):
            lasa_benchmark.run(cfg)
        assert not (out / "results.parquet").exists()


def test_configuration_errors_inside_fits_of_lasa_primitives_and_mnist_are_raised(tmp_path, mnist_dir):
    """Property: lasa_primitives (methods.lpvds_pqlf.eps=-1) and mnist (ds.eps=-1) raise the InvalidArgumentError
    of a bad fitter setting instead of storing every row as failed and exiting normally."""
    import lasa_primitives
    import mnist

    cfg = _compose("lasa_primitives", PRIMITIVES + ["~methods.seds", "~methods.lpvds_qlf", "methods.lpvds_pqlf.eps=-1",
                                                    f"+out_dir={tmp_path / 'prim'}"])  # fmt: skip
    with pytest.raises(InvalidArgumentError, match="eps"):
        lasa_primitives.run(cfg)
    assert not (tmp_path / "prim" / "results.parquet").exists()
    overrides = [o.format(mnist=mnist_dir) for o in MNIST]
    cfg = _compose("mnist", overrides + ["segmentation=none", "ds.eps=-1", f"+out_dir={tmp_path / 'mnist'}"])
    with pytest.raises(InvalidArgumentError, match="eps"):
        mnist.run(cfg)
    assert not (tmp_path / "mnist" / "results.parquet").exists()


def test_publish_into_a_finished_job_folder_publishes_its_stored_rows(tmp_path, no_fitting):
    """Property: lasa_benchmark with publish=true in a folder that already holds this job's finished rows (publish is
    not in the config hash, so the job is resumed) publishes those rows, summary and violins, without refitting."""
    import lasa_benchmark

    job = tmp_path / "job"
    overrides = BENCH + [f"paths.root={tmp_path / 'project'}", f"+out_dir={job}"]
    manifest = prepare_job(_compose("lasa_benchmark", overrides)).manifest
    rows = [{"experiment": "lasa_benchmark", "shape": "Angle", "method": "none+lpvds+none", "fold": 0, "seed": 0,
             "trajectory": i, "split": "train" if i == 0 else "test", "status": "ok", "segmentation": "none",
             "primitive": "lpvds", "modulation": "none", "E1": 1.0 + i, "E2": 0.1, "E3": 2.0, "DTWD": 3.0 * (i + 1),
             "final_error": 0.5, "reached": True, "time_s": 1.5, "n_steps": 1, "fit_s": 0.1,
             "stability_passed": True} for i in range(7)]  # fmt: skip
    write_table(pd.DataFrame(rows), job / "results.parquet", manifest=manifest)
    result = lasa_benchmark.run(_compose("lasa_benchmark", overrides + ["publish=true"]))
    assert result["skipped"]
    tables, figures = tmp_path / "project" / "results" / "tables", tmp_path / "project" / "results" / "figures"
    published = read_table(tables / "lasa_benchmark.parquet")
    stored = read_table(job / "results.parquet")
    pd.testing.assert_frame_equal(published, stored)
    assert (tables / "lasa_benchmark_summary.md").stat().st_size > 0
    assert (tables / "lasa_benchmark_summary.csv").stat().st_size > 0
    assert (figures / "lasa_benchmark_violins.png").stat().st_size > 0
    assert sorted(map(str, result["written"])) == sorted(map(str, [tables / "lasa_benchmark.parquet",
        tables / "lasa_benchmark_summary.md", tables / "lasa_benchmark_summary.csv",
        figures / "lasa_benchmark_violins.png"]))  # fmt: skip
    assert math.isclose(float(pd.read_csv(tables / "lasa_benchmark_summary.csv").E1_mean.iloc[1]), 4.5)


@pytest.fixture
def multirun():
    """A Hydra multirun context (HydraConfig set, mode MULTIRUN) for a composed configuration; reset afterwards."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    def make(name: str, overrides: list[str]):
        cfg = _compose(name, overrides, return_hydra_config=True)
        with open_dict(cfg):
            cfg.hydra.mode = RunMode.MULTIRUN
        HydraConfig.instance().set_config(cfg)
        return cfg

    yield make
    HydraConfig.instance().cfg = None


@pytest.mark.parametrize("script", ["lasa_metrics", "segment_lasa"])
def test_publish_in_a_multirun_raises_a_typed_error(script, multirun, tmp_path):
    """Property: publish=true in a multirun job of lasa_metrics / segment_lasa raises InvalidArgumentError (the
    store's prepare_job, as the other scripts), not a builtin ValueError, before anything is computed or written."""
    module = __import__(script)
    cfg = multirun(script, ["publish=true", "shapes=[Line]", f"paths.root={tmp_path}"])
    with pytest.raises(InvalidArgumentError, match="publish=true in a multirun"):
        module.run(cfg)
    assert not list(tmp_path.rglob("*.parquet"))


def test_lasa_metrics_statistics_are_the_columns_plot_metric_may_name():
    """Property: lasa_metrics.STATISTICS (what plot_metric is checked against) lists demo_statistics' columns."""
    import lasa_metrics

    from lfd_torch.data import load_lasa
    from lfd_torch.preprocess import Preprocess

    table = lasa_metrics.demo_statistics(load_lasa("Line"), Preprocess())
    assert tuple(table.columns) == lasa_metrics.STATISTICS
