"""Experiment entry points: run(cfg) directly and a tiny Hydra multirun merged by collect."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from lfd_torch.errors import InvalidArgumentError
from lfd_torch.store import KEY_COLUMNS, collect

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))


def test_lasa_metrics_run_writes_table_and_figure(tmp_path):
    import lasa_metrics

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_metrics", overrides=["shapes=[Line,Multi_Models_3]", f"+out_dir={tmp_path}"])
    result = lasa_metrics.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert len(table) == 14 and set(table["shape"]) == {"Line", "Multi_Models_3"}
    assert set(KEY_COLUMNS) <= set(table.columns) and table["git_sha"].notna().all()
    assert (tmp_path / "smoothing_area.png").stat().st_size > 0
    # smoothing with a window of 15 changes the path a little, never moves the goal
    assert (table["smoothing_area"] > 0).all() and (table["end_distance"] < 1e-9).all()
    assert len(result["table"]) == len(table)


@pytest.mark.slow
def test_lasa_metrics_multirun_and_collect(tmp_path):
    cmd = [
        sys.executable, str(ROOT / "experiments" / "lasa_metrics.py"), "-m", "preprocess.window=5,15",
        "shapes=[Line]", f"hydra.sweep.dir={tmp_path}",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, env={"OMP_NUM_THREADS": "1", "PATH": ""})
    merged = collect(tmp_path)
    assert len(merged) == 14 and set(merged["method"]) == {"savgol-w5", "savgol-w15"}
    # a wider window removes more: the smoothed path moves further from the raw one
    means = merged.groupby("method")["smoothing_area"].mean()
    assert means["savgol-w15"] > means["savgol-w5"]


def test_lasa_tasks_run_writes_rows_summary_and_figures(tmp_path):
    import lasa_tasks

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_tasks", overrides=["shapes=[Multi_Models_1]", "training=[one]", "n_random=12",
                                               "budget_s=40", "n_resample=60", f"+out_dir={tmp_path}"])  # fmt: skip
    result = lasa_tasks.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert set(KEY_COLUMNS) <= set(table.columns) and not table.duplicated(list(KEY_COLUMNS)).any()
    assert set(table["mode"]) == {"none", "full"} and {"demo", "random"} <= set(table["starts"])
    assert table["finished"].all() and (table["final_error"] < 1.0).all()
    rnd = table[table.starts == "random"]
    assert (rnd["pushes"] > 0).any()
    out = table[table.starts == "outside"]
    assert len(out) == 0 or out["recovery_samples"].notna().all()
    summary = (tmp_path / "summary.md").read_text()
    assert "Multi_Models_1" in summary and len(result["summary"]) == 1
    figs = {p.name for p in (tmp_path / "figures").iterdir()}
    for suffix in ("entropy.png", "steps.png", "modulation.png", "pushes.png", "tree.txt"):
        assert f"lasa_tasks_Multi_Models_1_{suffix}" in figs
    lib_dir = tmp_path / "libraries" / "Multi_Models_1_one"
    assert (lib_dir / "manifest.json").is_file()


def test_lasa_benchmark_one_training_demo_rows_and_shared_libraries(tmp_path, monkeypatch):
    import lasa_benchmark

    calls = []
    learn = lasa_benchmark.SkillLibrary.learn

    def counting(*args, **kwargs):
        calls.append(1)
        return learn(*args, **kwargs)

    monkeypatch.setattr(lasa_benchmark.SkillLibrary, "learn", counting)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_benchmark", overrides=["shapes=[Angle]", "fold=2", "segmentations=[none]",
                                                   "primitives=[lpvds]", f"+out_dir={tmp_path}"])  # fmt: skip
    result = lasa_benchmark.run(cfg)
    table = pd.read_parquet(tmp_path / "results.parquet")
    assert len(calls) == 1  # one library, shared by the two modulation variants
    assert len(table) == 2 * 7 and not table.duplicated(list(KEY_COLUMNS)).any()
    assert set(table.method) == {"none+lpvds+none", "none+lpvds+full"}
    train = table[table.split == "train"]
    assert set(train.trajectory) == {2} and set(table[table.split == "test"].trajectory) == {0, 1, 3, 4, 5, 6}
    assert table[["E1", "E2", "E3", "DTWD", "final_error"]].notna().all().all() and table.reached.all()
    assert len(result["table"]) == len(table)
    for fold, match in ((9, "0..6"), (-1, "fold"), ("a", "fold")):  # it was an index error naming no argument
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            bad = compose("lasa_benchmark", overrides=["shapes=[Angle]", f"fold={fold}", "segmentations=[none]",
                                                       "primitives=[lpvds]", f"+out_dir={tmp_path / 'bad'}"])
        with pytest.raises(InvalidArgumentError, match=match):
            lasa_benchmark.run(bad)
        assert not (tmp_path / "bad" / "results.parquet").exists()


def test_the_stored_quick_benchmark_is_what_the_code_computes(tmp_path):
    """The published quick-benchmark rows of one shape (``results/tables/lasa_benchmark.parquet``, written by
    ``+experiment=lasa_benchmark_publish``) are recomputed by the present code: a change that moves the segmented
    method's results fails here until the published tables are remade (``make results``). The table went stale once
    unnoticed: its BP-GM-HMM rows were those of a segmentation three changes old."""
    import lasa_benchmark

    stored = pd.read_parquet(ROOT / "results" / "tables" / "lasa_benchmark.parquet")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_benchmark", overrides=["shapes=[Angle]", "segmentations=[bp_gm_hmm]",
                                                   "primitives=[lpvds]", f"+out_dir={tmp_path}"])  # fmt: skip
    table = lasa_benchmark.run(cfg)["table"]
    keys = ["method", "split", "trajectory"]
    ref = stored[(stored["shape"] == "Angle") & stored.method.isin(set(table.method))].sort_values(keys)
    table = table.sort_values(keys)
    assert len(ref) == len(table) == 2 * 7 and list(ref.n_steps) == list(table.n_steps)
    for m in ("E1", "E2", "E3", "DTWD", "final_error", "time_s"):
        np.testing.assert_allclose(table[m].to_numpy(), ref[m].to_numpy(), rtol=1e-6, atol=1e-9, err_msg=m)


def test_the_stored_lasa_task_library_is_what_the_code_learns():
    """The published LASA-task library of Multi_Models_3 trained on demo 0 (``results/libraries/lasa_tasks``, written
    with the table by ``+experiment=lasa_tasks_publish``) is what the present code learns: the same pieces and
    attractors, and primitives that agree (a change that moves them fails here until ``make results``)."""
    import lasa_tasks

    from lfd_torch.data import load_lasa
    from lfd_torch.skills import SkillLibrary

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_tasks", overrides=["+experiment=lasa_tasks_publish"])
    shape = "Multi_Models_3"
    train = load_lasa(shape)[[int(cfg.train_demo)]]
    lib, _ = lasa_tasks.learn(cfg, train, instantiate(cfg.segmentation), (cfg.experiment, shape, "one", cfg.seed))
    stored = SkillLibrary.load(ROOT / "results" / "libraries" / "lasa_tasks" / f"{shape}_one")
    seg, ref = lib.segmentation, stored.segmentation
    assert [p.tolist() for p in seg.pieces] == [p.tolist() for p in ref.pieces]
    torch.testing.assert_close(seg.attractors, ref.attractors, rtol=1e-9, atol=1e-12)
    x = train.positions[0]
    for m in range(lib.n_steps):
        torch.testing.assert_close(lib.skills[m].primitive(x), stored.skills[m].primitive(x), rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_killed_multirun_resumes_to_the_table_of_an_uninterrupted_run(tmp_path):
    """A multirun killed after its first job, re-run with the same sweep dir, skips the finished job and ends with
    the same merged table as a run that was never interrupted."""
    import os
    import signal
    import time

    script = ROOT / "experiments" / "lasa_benchmark.py"

    def command(sweep: Path) -> list[str]:
        return [sys.executable, str(script), "-m", "shapes=[Angle],[Line],[CShape]", "segmentations=[none]",
                "primitives=[lpvds]", "modulations=[none]", "progress=false", f"hydra.sweep.dir={sweep}"]  # fmt: skip

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ref_dir, cut_dir = tmp_path / "ref", tmp_path / "cut"
    subprocess.run(command(ref_dir), check=True, env=env, capture_output=True, timeout=600)
    proc = subprocess.Popen(command(cut_dir), env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    first = cut_dir / "0" / "results.parquet"
    deadline = time.time() + 300
    while not first.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert first.exists() and not (cut_dir / "2" / "results.parquet").exists()
    from lfd_torch.store.sweep import main as collect_main, unfinished_jobs

    if unfinished_jobs(cut_dir):  # the killed job's folder exists without rows: publishing it is refused
        assert collect_main([str(cut_dir), "--out", str(tmp_path / "published.parquet")]) == 2
        assert not (tmp_path / "published.parquet").exists()
        assert collect_main([str(cut_dir), "--out", str(tmp_path / "forced.parquet"), "--force"]) == 0
    stamp = first.stat().st_mtime_ns
    subprocess.run(command(cut_dir), check=True, env=env, capture_output=True, text=True, timeout=600)
    assert first.stat().st_mtime_ns == stamp  # the finished job was skipped, not rewritten
    ref, got = collect(ref_dir), collect(cut_dir)
    cols = list(KEY_COLUMNS) + ["split", "E1", "E2", "E3", "DTWD", "final_error", "reached"]
    pd.testing.assert_frame_equal(got[cols], ref[cols], rtol=1e-6)
    assert "skipped" in (cut_dir / "0" / "lasa_benchmark.log").read_text()


@pytest.mark.parametrize("launcher", ["joblib", "submitit_local", "submitit_slurm", "ray"])
def test_launcher_configs_compose(launcher):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_benchmark", overrides=[f"hydra/launcher={launcher}"], return_hydra_config=True)
    target = cfg.hydra.launcher._target_
    assert target.startswith("hydra_plugins.") and target.split(".")[1].startswith(
        {"joblib": "hydra_joblib", "submitit_local": "hydra_submitit", "submitit_slurm": "hydra_submitit",
         "ray": "hydra_ray"}[launcher])  # fmt: skip
    if launcher == "joblib":
        assert cfg.hydra.launcher.n_jobs == -1


@pytest.mark.slow
def test_tiny_sweep_through_submitit_local(tmp_path):
    import os

    script = ROOT / "experiments" / "lasa_benchmark.py"
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, str(script), "-m", "hydra/launcher=submitit_local", "fold=0,3", "shapes=[Line]",
           "segmentations=[none]", "primitives=[lpvds]", "modulations=[none]", "progress=false",
           f"hydra.sweep.dir={sweep}"]  # fmt: skip
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, timeout=600)
    table = collect(sweep)
    assert sorted(set(table.fold)) == [0, 3] and len(table) == 14
    assert set(table[table.split == "train"].trajectory) == {0, 3}


@pytest.mark.parametrize("preset", ["sweep_segmentation", "sweep_modulation"])
def test_hyperparameter_sweep_presets_compose_and_tag_their_methods(preset):
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("lasa_benchmark", overrides=[f"+experiment={preset}"], return_hydra_config=True)
    params = OmegaConf.to_container(cfg.hydra.sweeper.params)
    assert cfg.hydra.mode.name == "MULTIRUN" and len(params) >= 3
    tag = str(cfg.tag)
    assert tag and "$" not in tag  # every swept setting is resolved into the method name, so collect keeps rows apart


def test_attractor_checks_of_the_seed_bench_against_closed_forms():
    """``attractor_offsets`` and ``route_coverage`` on two parallel straight demonstrations 0.1 apart (span
    sqrt(1 + 0.01)), one route of two steps switching at x = 0.5: the mean end point (0.5, 0.05) is 0.05 from either
    path, the best sample of the step 0.1 (a point of one path is 0.1 from the other), and no sample has both paths
    within 2 % of the span (0 %); an attractor on one path is 0.1 from the other and 0 from the nearest; with the
    second demonstration on top of the first, everything lies on both."""
    import types

    import bench_segmentation_seeds as bench

    x = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    a = torch.stack([x, torch.zeros_like(x)], -1)
    b = torch.stack([x, torch.full_like(x, 0.1)], -1)
    pieces = [torch.tensor([[0, 0, 51], [1, 51, 101]]), torch.tensor([[0, 0, 51], [1, 51, 101]])]
    seg = types.SimpleNamespace(n_steps=2, pieces=pieces, routes=((0, 1),), route_of=torch.tensor([0, 0]),
                                attractors=torch.tensor([[0.5, 0.05], [1.0, 0.05]], dtype=torch.float64))
    span = math.sqrt(1.01)
    worst, bound, nearest = bench.attractor_offsets(seg, [a, b])
    assert worst == pytest.approx(100 * 0.05 / span) and bound == pytest.approx(100 * 0.1 / span)
    assert nearest == pytest.approx(100 * 0.05 / span)
    assert bench.route_coverage(seg, [a, b]) == 0.0
    seg.attractors = torch.tensor([[0.5, 0.0], [1.0, 0.0]], dtype=torch.float64)  # on path a, 0.1 from path b
    worst, _, nearest = bench.attractor_offsets(seg, [a, b])
    assert worst == pytest.approx(100 * 0.1 / span) and nearest == 0.0
    assert bench.attractor_offsets(seg, [a, a.clone()]) == (0.0, 0.0, 0.0)
    assert bench.route_coverage(seg, [a, a.clone()]) == 100.0


def test_synthetic_study_rows_do_not_depend_on_the_number_of_workers():
    """``synthetic_study(jobs=2)`` (worker processes) gives the rows of the serial loop, in the same order (only
    the wall times differ)."""
    import bench_segmentation as bench

    kw = dict(seeds=2, methods=("segment",), families=("straight_dwell_2d",), n_demos=(1,))
    serial, pooled = bench.synthetic_study(**kw), bench.synthetic_study(**kw, jobs=2)
    assert len(serial) == 2
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in serial] == \
        [{k: v for k, v in r.items() if k != "seconds"} for r in pooled]


def test_segment_options_parse_numbers_flags_and_names():
    """``--segment-option`` values: None/True/False, ints, floats, and any other word as a string (noise_model)."""
    import bench_segmentation as bench

    got = bench.segment_options(["extra_dof=2", "robust_dof=None", "dwell_cue=False", "direction_noise=0.1",
                                 "noise_model=white"])
    assert got == {"extra_dof": 2, "robust_dof": None, "dwell_cue": False, "direction_noise": 0.1,
                   "noise_model": "white"}
    assert isinstance(got["extra_dof"], int)


def test_segment_settings_are_the_signature_defaults_overlaid_by_the_options():
    """What a benchmark table records as ``segment_settings``: every keyword of segment() but the generator, from
    the signature (checked against inspect here by name and value, with the yaml config as a second reference for
    the emission keys), the options on top; an unknown keyword is refused before any run."""
    import inspect

    import bench_segmentation as bench
    from omegaconf import OmegaConf

    from lfd_torch.segmentation import segment

    params = inspect.signature(segment).parameters
    got = bench.segment_settings({"slope_scale": 3.0, "block_emission": False})
    assert set(got) == {k for k in params if k not in ("demos", "generator")}
    assert got["slope_scale"] == 3.0 and got["block_emission"] is False
    assert all(got[k] == params[k].default for k in got if k not in ("slope_scale", "block_emission"))
    yaml = OmegaConf.load(ROOT / "conf/segmentation/bp_gm_hmm.yaml")
    plain = bench.segment_settings({})
    assert (plain["block_emission"], plain["position_mixture"]) == (yaml.block_emission, yaml.position_mixture)
    with pytest.raises(SystemExit, match="no keyword bogus"):
        bench.segment_settings({"bogus": 1})


def test_correlated_noise_cases_share_the_paths_of_the_white_ones():
    """``synthetic_study(noise_correlation=rho)``: the same paths and switches as the white cases, other noise."""
    import bench_segmentation as bench

    kw = dict(seeds=1, methods=("ruptures",), families=("straight_const_2d",), n_demos=(1,))
    white, ar1 = bench.synthetic_study(**kw), bench.synthetic_study(**kw, noise_correlation=0.5)
    assert white[0]["true_switches"] == ar1[0]["true_switches"] and white[0]["lengths"] == ar1[0]["lengths"]
    assert white[0]["noise_fraction"] == ar1[0]["noise_fraction"]


def test_noise_scale_cases_share_the_paths_and_record_the_new_level():
    """``synthetic_study(noise_scale=s)``: the same paths and switches as the default cases, the recorded noise level
    s times theirs; a level that is not positive is refused before any case runs."""
    import bench_segmentation as bench

    kw = dict(seeds=1, methods=("ruptures",), families=("straight_const_2d",), n_demos=(1,))
    plain, quiet = bench.synthetic_study(**kw), bench.synthetic_study(**kw, noise_scale=0.1)
    assert plain[0]["true_switches"] == quiet[0]["true_switches"] and plain[0]["lengths"] == quiet[0]["lengths"]
    assert quiet[0]["noise_fraction"] == pytest.approx(0.1 * plain[0]["noise_fraction"], rel=1e-12)
    with pytest.raises(SystemExit, match="noise-scale"):
        bench.synthetic_study(**kw, noise_scale=0.0)


def test_held_out_families_run_through_the_synthetic_study():
    """``--families`` takes the held-out families (``HELD_OUT_FAMILIES``): their rows carry the rounded generator's
    truth (the drawn switches), and the default family list stays the 14 benchmark families."""
    import bench_segmentation as bench
    from lfd_torch.segmentation.synthetic import FAMILIES, HELD_OUT_FAMILIES, SLOWING_FAMILIES

    rows = bench.synthetic_study(seeds=1, methods=("ruptures",), families=("rounded_vary_2d",), n_demos=(2,))
    syn = HELD_OUT_FAMILIES["rounded_vary_2d"](torch.Generator().manual_seed(bench.data_seed("rounded_vary_2d", 0)), 2)
    assert rows[0]["family"] == "rounded_vary_2d" and rows[0]["true_switches"] == syn.switch_times.tolist()
    assert set(bench.ALL_FAMILIES) == set(FAMILIES) | set(HELD_OUT_FAMILIES) | set(SLOWING_FAMILIES)
    assert len(FAMILIES) == 14


def test_seed_stable_is_the_issue_7_rule():
    """``seed_stable``: every demonstration's most common step count must occur on >= 90 % of the seeds (9 of 10);
    one demonstration at 8 of 10 makes the case unstable, whatever the others do."""
    import bench_segmentation_seeds as bench

    steady = [[3, 4]] * 9 + [[4, 4]]
    assert bench.seed_stable(steady) == ([3, 4], True)
    shaky = [[3, 4]] * 8 + [[2, 4], [4, 4]]
    assert bench.seed_stable(shaky) == ([3, 4], False)
    assert bench.seed_stable([[5]] * 10) == ([5], True)
    assert bench.seed_stable([[2], [3]] * 5)[1] is False


def test_diagnose_segmentation_scores_the_returned_labelling_as_the_sampler_does():
    """The diagnostic's score of the returned labelling is the collapsed score the sampler reports for it (the map
    search's objective), the true labelling of the same grid gets a finite score of its own, and the gap split into
    the score's terms adds up to the gap."""
    import diagnose_segmentation as diag
    from bench_segmentation import data_seed

    with diag.captured_runs() as runs:
        pass
    assert runs == []
    r = diag.score_gap("straight_const_2d", 0, 1, selection="map", position_weight=None, straight_weight=0.5)
    syn_seg = diag.segment(
        diag.FAMILIES["straight_const_2d"](torch.Generator().manual_seed(data_seed("straight_const_2d", 0)), 1).demos,
        generator=torch.Generator().manual_seed(0), selection="map", position_weight=None, straight_weight=0.5,
    )
    assert r["score_found"] == pytest.approx(syn_seg.info["collapsed_log_prob"], abs=0.05)
    assert math.isfinite(r["score_true"]) and r["true_steps"] == 5
    assert r["gap"] == pytest.approx(r["score_found"] - r["score_true"], abs=0.11)
    assert sum(r["gap_parts"].values()) == pytest.approx(r["gap"], abs=0.5)  # the terms add up to the score
    assert set(r["gap_parts"]) == {"emission", "dwell", "transitions", "initial", "features"}


def test_diagnose_convergent_fields_affine_part_is_the_sampler_field_evidence():
    """``diagnose_convergent_fields``: its affine spike-and-slab evidence of a labelling (per state, from its own
    statistics) is the sampler's Gaussian field evidence of that labelling (``robust_dof=None``, white tolerance),
    for the returned and the true labelling; each state's attractor g_k is the mean of its runs' last grid points,
    found here with a loop; the convergent evidence is finite and differs from the affine one."""
    import diagnose_convergent_fields as conv
    import diagnose_segmentation as diag

    seg, run, truth = diag.case_labellings("straight_const_2d", 0, 1, robust_dof=None)
    for s in (seg.sampler.states, truth):
        K = int(s.max()) + 1
        onehot = (torch.nn.functional.one_hot(s, K).to(run.dtype) * run.valid.unsqueeze(-1)).reshape(1, -1, K)
        age, w, _ = run._score_view(s[None])
        want = float(run._field_evidence(age, w, onehot).sum())
        got = conv.field_evidence(run, s, 0.05)
        assert got["affine"] == pytest.approx(want, abs=1e-8)
        assert math.isfinite(got["convergent"]) and abs(got["convergent"] - got["affine"]) > 1e-3
        ends = {}
        for i in range(run.N):
            n = int(run.lengths[i])
            for t in range(n):
                if t == n - 1 or int(s[i, t + 1]) != int(s[i, t]):
                    ends.setdefault(int(s[i, t]), []).append(run.obs.z[i, t, : run.d])
        g = conv.attractors(run, s)
        assert sorted(g) == sorted(ends)
        for k, pts in ends.items():
            assert torch.allclose(g[k], torch.stack(pts).mean(0))
        # the convergent part, assembled here per state from regressors built sample by sample: the spike (offset
        # regressor) and the slab (the softened unit vector from g_k, prior mean -I, the slope block of the prior)
        from lfd_torch.segmentation.field import FieldPrior, field_log_marginal_likelihood, straight_field_prior

        d, eps, total = run.d, 0.05, 0.0
        slab = FieldPrior(mean=-torch.eye(d, dtype=run.dtype), row_covariance=run.prior.row_covariance[:d, :d],
                          dof=run.prior.dof, scale=run.prior.scale)
        for k, pts in ends.items():
            gk = torch.stack(pts).mean(0)
            zs, cs, us, ws = [], [], [], []
            for i in range(run.N):
                for t in range(int(run.lengths[i])):
                    if int(s[i, t]) == k:
                        r = run.obs.z[i, t, :d] - gk
                        zs.append(run.obs.z[i, t, d:])
                        cs.append(r / math.sqrt(float(r @ r) + eps**2))
                        us.append(run.obs.u[i, t])
                        ws.append(float(run.obs.w[i, t]))
            w_ = torch.tensor(ws, dtype=run.dtype)

            def evidence(prior, x, u=torch.stack(us)):
                xw = x * w_.unsqueeze(-1)
                return field_log_marginal_likelihood(prior, torch.tensor(float(len(ws)), dtype=run.dtype),
                                                     xw.T @ x, (u * w_.unsqueeze(-1)).T @ x,
                                                     (u * w_.unsqueeze(-1)).T @ u)
            spike = math.log(0.5) + evidence(straight_field_prior(run.prior), torch.stack(zs))
            total += float(torch.logaddexp(spike, math.log(0.5) + evidence(slab, torch.stack(cs))))
        assert got["convergent"] == pytest.approx(total, abs=1e-8)


def test_diagnose_position_cut_gain_is_the_sampler_position_score():
    """``diagnose_position.cut_gain`` of the L-shaped path is the sampler's position evidence, recomputed here from
    the NIW kernel with the sampler's standardisation and the two labellings written out by hand (the mixture form
    is tested in ``tests/test_segmentation.py``)."""
    import diagnose_position as diag

    from lfd_torch.gmm import niw_log_marginal_likelihood, niw_prior_from_data, sufficient_statistics

    n, tau = 30, 1.0 / 3.0
    path = diag.l_path(n, 0.01)
    x = path - path.mean(0)
    x = x / x.square().sum(-1).mean().sqrt()  # the sampler's standardisation: RMS distance to the centre 1
    prior = niw_prior_from_data(x, covariance_scale=0.05)
    labels = [torch.cat([torch.zeros(n), torch.full((n,), 2.0)]).long(),
              torch.cat([torch.zeros(n // 2), torch.ones(n - n // 2), torch.full((n,), 2.0)]).long()]
    scores = [float(niw_log_marginal_likelihood(prior, *sufficient_statistics(
        x[None], tau * torch.nn.functional.one_hot(lab, 3).to(x)[None])).sum()) for lab in labels]
    assert diag.cut_gain(path, n, tau, False) == pytest.approx(scores[1] - scores[0], abs=1e-6)


def test_chord_turn_is_the_corner_angle_and_the_arc_fraction():
    """``chord_turn`` (the scooping turn study): at a corner between straight legs longer than h L it is the corner's
    angle; on a circular arc turning by phi over a length l_a it is phi h L / l_a (the two chords' directions are
    those of their midpoints, h L of arc apart). Closed forms."""
    import math

    import bench_scooping_segmentation as bench

    theta = math.radians(70.0)  # a polyline: 1 m along x, then 1 m at 70 degrees
    s = torch.linspace(0.0, 1.0, 501, dtype=torch.float64)[:, None]
    leg_b = torch.tensor([math.cos(theta), math.sin(theta)], dtype=torch.float64)
    x = torch.cat([torch.cat([s - 1.0, torch.zeros_like(s)], -1), s[1:] * leg_b], 0)
    assert bench.chord_turn(x, 500, 0.0125) == pytest.approx(70.0, abs=1e-6)
    assert bench.chord_turn(x, 500, 0.2) == pytest.approx(70.0, abs=1e-6)
    assert bench.chord_turn(x, 250, 0.1) == pytest.approx(0.0, abs=1e-6)  # inside a leg, 0.5 m from the corner
    phi = torch.linspace(0.0, math.pi, 2001, dtype=torch.float64)  # a half circle: L = pi, 180 degrees
    arc = torch.stack([torch.cos(phi), torch.sin(phi)], -1)
    assert bench.chord_turn(arc, 1000, 0.05) == pytest.approx(180.0 * 0.05, rel=1e-3)  # h L = l_a / 20: 9 degrees


def test_readme_slowing_table_is_the_stored_table():
    """The README's held-out slowing table (every switch found, 1 / 4 demonstrations, per method) is what the stored
    ``bench_segmentation_held_out_slowing.json`` says, and that table holds all 140 cases of the 7 families."""
    import json
    from pathlib import Path

    from lfd_torch.segmentation.synthetic import SLOWING_FAMILIES

    root = Path(__file__).resolve().parents[1]
    table = json.loads((root / "results/tables/bench_segmentation_held_out_slowing.json").read_text())
    rows = [r for r in table["synthetic"] if r["method"] == "segment"]
    assert {r["family"] for r in rows} == set(SLOWING_FAMILIES) and len(rows) == 140
    readme = (root / "README.md").read_text()
    labels = {"segment": "`segment` (defaults)", "ruptures": "ruptures PELT, rbf cost",
              "hmmlearn": "hmmlearn GaussianHMM, states by BIC"}
    for method, label in labels.items():
        mine = [r for r in table["synthetic"] if r["method"] == method]
        share = {n: round(100 * sum(bool(r["all_switches"]) for r in mine if r["n_demos"] == n)
                          / sum(r["n_demos"] == n for r in mine)) for n in (1, 4)}
        overall = round(100 * sum(bool(r["all_switches"]) for r in mine) / len(mine))
        line = next(ln for ln in readme[readme.index("| slowing, 140 cases"):].splitlines()
                    if ln.startswith(f"| {label} |"))
        cell = [c.strip() for c in line.strip("|").split("|")][2]
        assert cell.replace("*", "").startswith(f"{overall} % ({share[1]} % / {share[4]} %)"), (method, cell)


def test_oracle_leg_costs_and_partition_against_polyfit_and_ruptures():
    """The known-count oracle's leg costs are numpy.polyfit's residual sums of squares (every candidate pair, an
    irregular last candidate included), its dynamic programme returns the partition of ruptures' Dynp under the same
    cost, and on noise-free straight legs at constant speed it puts every switch on its corner."""
    import numpy as np
    import ruptures as rpt

    from oracle_switches import best_partition, oracle_switches, segment_costs

    g = torch.Generator().manual_seed(3)
    x = torch.randn(37, 2, generator=g, dtype=torch.float64).cumsum(0)
    cand, cost = segment_costs(x, 2, 2, 5)
    assert cand == list(range(0, 37, 2)) + [37]

    def rss(seg: np.ndarray, degree: int) -> float:
        t = np.arange(len(seg))
        return float(sum(((np.polyval(np.polyfit(t, seg[:, a], degree), t) - seg[:, a]) ** 2).sum()
                         for a in range(seg.shape[1])))

    for i, a in enumerate(cand):
        for j, b in enumerate(cand):
            if b - a >= 5:
                assert float(cost[i, j]) == pytest.approx(rss(x[a:b].numpy(), 2), abs=1e-9), (a, b)
            else:
                assert math.isinf(float(cost[i, j])), (a, b)

    class PolyCost(rpt.base.BaseCost):
        model, min_size = "poly1", 6

        def fit(self, signal):
            self.signal = signal
            return self

        def error(self, start, end):
            return rss(self.signal[start:end], 1)

    y = torch.randn(60, 2, generator=g, dtype=torch.float64).cumsum(0)
    cand, cost = segment_costs(y, 1, 3, 6)
    mine = best_partition(cand, [cost] * 3)
    theirs = rpt.Dynp(custom_cost=PolyCost(), min_size=6, jump=3).fit(y.numpy()).predict(n_bkps=2)[:-1]
    assert mine == theirs

    corners = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 0.7], [0.2, 1.2]], dtype=torch.float64)
    legs = [torch.linspace(0, 1, n + 1, dtype=torch.float64)[:-1, None] * (b - a) + a
            for a, b, n in zip(corners[:-1], corners[1:], (100, 70, 94))]
    path = torch.cat(legs + [corners[-1:]])
    assert oracle_switches(path, [1, 1, 1], grid="full", stride=2, min_length=10) == [100, 170]
    found = oracle_switches(path, [1, 1, 1], grid="average", stride=2, min_length=10)  # blocks of k = 4 samples
    assert found[0] == 100 and found[1] in (168, 172)  # 170 lies inside the block 168-171


def test_readme_oracle_figures_are_the_stored_tables():
    """The README's known-count oracle shares (every switch found, all 140 constant-speed cases) are what the stored
    ``oracle_switches_*.json`` tables say, and each table holds the 140 cases of the seven families; so are its counts
    of the misses whose true steps the block emission prefers (``diagnose_block_emission_missed.json``)."""
    import json

    from oracle_switches import CONSTANT_SPEED

    readme = (ROOT / "README.md").read_text()
    text = readme[readme.index("How well the constant-speed switches can be placed at all"):][:1500]
    for name in ("shape_full", "shape_average", "shape_subsample", "generic_full"):
        table = json.loads((ROOT / f"results/tables/oracle_switches_{name}.json").read_text())
        rows = table["cases"]
        assert len(rows) == 140 and {r["family"] for r in rows} == set(CONSTANT_SPEED), name
        share = 100 * sum(r["all_switches"] for r in rows) / len(rows)
        assert f"{share:.1f} %" in text, (name, share)
    block = json.loads((ROOT / "results/tables/diagnose_block_emission_missed.json").read_text())["cases"]
    text = readme[readme.index("Scored as that emission"):][:900]
    assert len(block) == 38
    assert f"in {sum(r['block_gap'] < 0 for r in block)} of the defaults' 38 misses" in text
    assert f"(the sampler's direction emission: {sum(r['sampler_emission_gap'] < 0 for r in block)})" in text
    assert f"still win in {sum(r['block_total_gap'] < 0 for r in block)} of the 38" in text


def test_block_emission_is_the_gaussian_of_its_written_out_model():
    """The block-mean emission of ``diagnose_block_emission.py`` for one demonstration with one switch, straight then
    affine, is the Gaussian density of the model written out by hand: x_j = x_0 + (d + delta) S0_j + c [j > 3] +
    B Z1_j + W_j + e_j per axis, S0 / Z1 the path length / regressors each state owned, c the corner's free
    displacement, W the affine state's random walk (scipy's multivariate normal as the reference)."""
    import numpy as np
    from scipy.stats import multivariate_normal

    from diagnose_block_emission import block_evidence

    g = torch.Generator().manual_seed(5)
    n, d = 8, 2
    s = torch.tensor([0.0, 0.1, 0.2, 0.3, 0.42, 0.5, 0.61, 0.7], dtype=torch.float64)
    m = torch.tensor([3, 4, 4, 4, 4, 4, 4, 3], dtype=torch.float64)
    z = torch.cat([torch.randn(n, d, generator=g, dtype=torch.float64), torch.ones(n, 1, dtype=torch.float64)], -1)
    x = torch.randn(n, d, generator=g, dtype=torch.float64).cumsum(0) * 0.1
    data = [{"x": x, "s": s, "m": m, "z": z, "noise": 0.05}]
    labels = torch.tensor([[0, 0, 0, 0, 1, 1, 1, 1]])
    tol, spread, slope = 0.2, 0.05, 1.0
    mine = block_evidence(data, labels, tolerance=tol, demo_spread=spread, slope_scale=slope, components=(0, 1))

    ds = (s[1:] - s[:-1]).numpy()
    S0 = np.concatenate([[0.0], np.cumsum(ds * (np.arange(n - 1) < 3))])  # increments 0-1, 1-2, 2-3
    own1 = (np.arange(n - 1) >= 4).astype(float)  # increments 4-5, 5-6, 6-7; 3-4 is the corner
    zmid = 0.5 * (z[1:] + z[:-1]).numpy()
    Z1 = np.concatenate([np.zeros((1, d + 1)), np.cumsum((ds * own1)[:, None] * zmid, 0)])
    corner = (np.arange(n) > 3).astype(float)
    walk = np.concatenate([[0.0], np.cumsum((ds * own1 * tol) ** 2)])
    cov = (np.ones((n, n)) + (1.0 / d + spread**2) * np.outer(S0, S0) + ds[3] ** 2 * np.outer(corner, corner)
           + Z1 @ np.diag([slope**2] * d + [1.0]) @ Z1.T + np.minimum.outer(walk, walk)
           + np.diag(0.05**2 / m.numpy()))
    ref = sum(multivariate_normal(np.full(n, x[0, a].item()), cov).logpdf(x[:, a].numpy()) for a in range(d))
    assert mine == pytest.approx(ref, abs=1e-8)
