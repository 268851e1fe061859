"""Results store: atomic writes, run manifest, results tables, sweep collection."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from omegaconf import OmegaConf

import lfd_torch
from lfd_torch.errors import LfdError, StoreError
from lfd_torch.store import (
    KEY_COLUMNS,
    MANIFEST_FIELDS,
    PROVENANCE_COLUMNS,
    PartialSweepWarning,
    atomic_path,
    atomic_write,
    canonical_json,
    collect,
    config_hash,
    git_sha,
    read_manifest,
    read_table,
    run_manifest,
    write_table,
)
from lfd_torch.store import manifest as manifest_module
from lfd_torch.store.sweep import main as collect_main

REPO_ROOT = Path(__file__).resolve().parents[1]
SHA_RE = re.compile(r"^[0-9a-f]{40}(-dirty)?$")


def _leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


# --------------------------------------------------------------------------------------------- atomic writes


def test_atomic_write_replaces_and_creates_parents(tmp_path: Path) -> None:
    target = tmp_path / "a" / "b" / "out.bin"
    returned = atomic_write(target, lambda tmp: tmp.write_bytes(b"new"))
    assert returned == target
    assert target.read_bytes() == b"new"
    atomic_write(target, lambda tmp: tmp.write_bytes(b"newer"))
    assert target.read_bytes() == b"newer"
    assert _leftovers(target.parent) == []


def test_atomic_write_keeps_old_file_when_writer_fails_midway(tmp_path: Path) -> None:
    target = tmp_path / "model.pt"
    target.write_bytes(b"old content")
    seen: list[Path] = []

    def crashing_writer(tmp: Path) -> None:
        seen.append(tmp)
        with open(tmp, "wb") as handle:
            handle.write(b"half of the new")
            handle.flush()
        assert tmp.exists() and tmp.parent == target.parent  # written beside the target, not over it
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(target, crashing_writer)
    assert target.read_bytes() == b"old content"
    assert not seen[0].exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]


def test_atomic_path_cleans_up_on_keyboard_interrupt_and_missing_output(tmp_path: Path) -> None:
    target = tmp_path / "fig.png"
    target.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise KeyboardInterrupt
    with pytest.raises(StoreError, match="did not create"):
        with atomic_path(target):
            pass
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]


def test_atomic_temp_names_are_unique_hidden_and_in_place(tmp_path: Path) -> None:
    names = set()
    for _ in range(3):
        with atomic_path(tmp_path / "x.parquet") as tmp:
            assert tmp.parent == tmp_path
            assert tmp.name.startswith(".x.parquet.") and tmp.name.endswith(".tmp")
            assert str(os.getpid()) in tmp.name
            names.add(tmp.name)
            tmp.write_bytes(b"1")
    assert len(names) == 3


# ------------------------------------------------------------------------------------------ config hash


def test_config_hash_stable_across_key_order_and_containers() -> None:
    a = {"ds": {"name": "lpvds", "eps": 1e-3, "k": [1, 2, 3]}, "data": {"shape": "Sshape"}, "n": 7}
    b = {"n": 7, "data": {"shape": "Sshape"}, "ds": {"k": [1, 2, 3], "eps": 1e-3, "name": "lpvds"}}
    h = config_hash(a)
    assert h == config_hash(b) == config_hash(OmegaConf.create(b))
    assert re.fullmatch(r"[0-9a-f]{12}", h)
    # Tuples, numpy and torch scalars hash like their plain equivalents.
    c = {"ds": {"name": "lpvds", "eps": np.float64(1e-3), "k": (1, torch.tensor(2), np.int64(3))},
         "data": {"shape": "Sshape"}, "n": 7}
    assert config_hash(c) == h
    # Interpolations are resolved before hashing.
    interp = OmegaConf.create({"n": 7, "m": "${n}"})
    assert config_hash(interp) == config_hash({"n": 7, "m": 7})
    assert config_hash(a, length=64).startswith(h)


def test_config_hash_differs_on_change() -> None:
    base = {"ds": {"name": "lpvds", "eps": 1e-3, "k": [1, 2, 3]}, "n": 7}
    h = config_hash(base)
    changed = [
        {"ds": {"name": "seds", "eps": 1e-3, "k": [1, 2, 3]}, "n": 7},
        {"ds": {"name": "lpvds", "eps": 1e-4, "k": [1, 2, 3]}, "n": 7},
        {"ds": {"name": "lpvds", "eps": 1e-3, "k": [3, 2, 1]}, "n": 7},
        {"ds": {"name": "lpvds", "eps": 1e-3, "k": [1, 2, 3]}, "n": 7, "extra": None},
        {"ds": {"name": "lpvds", "eps": 1e-3, "k": [1, 2, 3]}, "n": "7"},
    ]
    hashes = {config_hash(c) for c in changed}
    assert h not in hashes and len(hashes) == len(changed)


def test_config_hash_ignores_seed_and_hydra_by_default() -> None:
    cfg = {"n": 1, "seed": 3, "hydra": {"run": {"dir": "/tmp/x"}}}
    assert config_hash(cfg) == config_hash({"n": 1})
    assert config_hash(cfg, exclude=()) != config_hash({"n": 1}, exclude=())
    assert '"seed":3' in canonical_json(cfg)


@pytest.mark.parametrize(
    "bad",
    [{"x": object()}, {"x": {1: "a", "1": "b"}}, OmegaConf.create({"x": "???"}), OmegaConf.create({"x": "${nope}"})],
)
def test_config_hash_rejects_unhashable_configs(bad) -> None:
    with pytest.raises(StoreError):
        config_hash(bad)


# --------------------------------------------------------------------------------------------- manifest


def test_run_manifest_fields() -> None:
    cfg = OmegaConf.create({"seed": 5, "ds": {"name": "lpvds"}})
    manifest = run_manifest(cfg, 5)
    assert tuple(manifest) == MANIFEST_FIELDS
    assert manifest["seed"] == 5 and isinstance(manifest["seed"], int)
    assert manifest["config_hash"] == config_hash(cfg)
    assert manifest["package_version"] == lfd_torch.__version__
    assert manifest["torch_version"] == torch.__version__
    assert manifest["python_version"] == ".".join(map(str, sys.version_info[:3]))
    stamp = pd.Timestamp(manifest["timestamp"])
    assert stamp.tzinfo is not None and stamp.utcoffset() == pd.Timedelta(0)
    assert abs(pd.Timestamp.now(tz="UTC") - stamp) < pd.Timedelta(minutes=5)
    assert manifest["git_sha"] == "unknown" or SHA_RE.match(manifest["git_sha"])
    assert run_manifest(None, np.int64(2))["seed"] == 2


@pytest.mark.parametrize("seed", [True, 1.5, "3"])
def test_run_manifest_rejects_bad_seed(seed) -> None:
    with pytest.raises(StoreError, match="seed"):
        run_manifest({}, seed)


def test_run_manifest_rejects_seed_disagreeing_with_config() -> None:
    with pytest.raises(StoreError, match="disagrees"):
        run_manifest({"seed": 1}, 2)


def _git(repo: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false", *args],
        cwd=repo, capture_output=True, text=True, check=True,
    )
    return done.stdout.strip()


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_git_sha_clean_dirty_and_outside_a_repository(tmp_path: Path, monkeypatch) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    (repo / "f.txt").write_text("a")
    _git(repo, "add", "f.txt")
    _git(repo, "commit", "-q", "-m", "c")
    head = _git(repo, "rev-parse", "HEAD")
    assert manifest_module._git_sha_uncached(str(repo)) == head
    (repo / "untracked.txt").write_text("u")  # untracked files do not make the tree dirty
    assert manifest_module._git_sha_uncached(str(repo)) == head
    (repo / "f.txt").write_text("b")
    assert manifest_module._git_sha_uncached(str(repo)) == f"{head}-dirty"
    outside = tmp_path / "plain"
    outside.mkdir()
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))  # never look above tmp_path
    assert manifest_module._git_sha_uncached(str(outside)) == "unknown"


def test_git_sha_falls_back_to_unknown_without_git(monkeypatch, tmp_path: Path) -> None:
    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")

    monkeypatch.setattr(manifest_module.subprocess, "run", no_git)
    assert manifest_module._git_sha_uncached(str(tmp_path)) == "unknown"


def test_git_sha_is_cached_per_process(monkeypatch, tmp_path: Path) -> None:
    calls = []
    real_run = subprocess.run

    def counting_run(*args, **kwargs):
        calls.append(args)
        return real_run(*args, **kwargs)

    monkeypatch.setattr(manifest_module.subprocess, "run", counting_run)
    first = git_sha(tmp_path)
    n_first = len(calls)
    assert git_sha(tmp_path) == first
    assert len(calls) == n_first  # second lookup served from the cache
    assert git_sha() == git_sha(REPO_ROOT)


# ----------------------------------------------------------------------------------------------- tables


def _rows(methods=("SEDS", "LPV-DS"), n_traj=3, seed=0, shape="Sshape", generator=None, offset=0.0):
    g = generator if generator is not None else torch.Generator().manual_seed(seed)
    rows = []
    for method in methods:
        for trajectory in range(n_traj):
            e = torch.rand(3, generator=g, dtype=torch.float64).tolist()
            rows.append(
                {
                    "experiment": "lasa",
                    "shape": shape,
                    "method": method,
                    "fold": 0,
                    "seed": seed,
                    "trajectory": trajectory,
                    "split": "train" if trajectory == 0 else "test",
                    "E1": e[0] + offset,
                    "E2": e[1],
                    "E3": e[2],
                }
            )
    return rows


def _manifest(seed=0, cfg=None):
    return run_manifest(cfg if cfg is not None else {"seed": seed, "ds": "lpvds"}, seed)


def test_table_round_trip(tmp_path: Path, generator) -> None:
    rows = _rows(generator=generator)
    rows[2]["E3"] = float("nan")  # a failed metric stays a NaN
    manifest = _manifest()
    path = write_table(rows, tmp_path / "results.parquet", manifest=manifest)
    table = read_table(path)
    expected = pd.DataFrame(rows)
    for column in ("config_hash", "package_version", "git_sha"):
        expected[column] = manifest[column]
    pd.testing.assert_frame_equal(table, expected, check_dtype=False)
    assert table["E1"].dtype == np.float64 and table["fold"].dtype == np.int64
    assert read_manifest(path) == manifest
    # DataFrame input gives the same table; a second write reproduces it exactly.
    write_table(pd.DataFrame(rows), tmp_path / "again.parquet", manifest=manifest)
    pd.testing.assert_frame_equal(read_table(tmp_path / "again.parquet"), table)
    assert _leftovers(tmp_path) == []


def test_write_table_named_index_becomes_columns(tmp_path: Path) -> None:
    frame = pd.DataFrame(_rows()).set_index(list(KEY_COLUMNS))
    write_table(frame, tmp_path / "t.parquet", manifest=_manifest())
    assert set(KEY_COLUMNS) <= set(read_table(tmp_path / "t.parquet").columns)


def test_write_table_without_manifest_needs_provenance(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="config_hash"):
        write_table(_rows(), tmp_path / "t.parquet")
    rows = [dict(r, config_hash="abc", package_version="0", git_sha="unknown") for r in _rows()]
    assert len(read_table(write_table(rows, tmp_path / "t.parquet"))) == len(rows)
    assert read_manifest(tmp_path / "t.parquet") is None


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda rows: [{k: v for k, v in r.items() if k != "shape"} for r in rows], r"missing.*shape"),
        (lambda rows: rows + [dict(rows[0])], "share their key"),
        (lambda rows: [dict(r, method=None) if i == 1 else r for i, r in enumerate(rows)], "null"),
        (lambda rows: [dict(r, config_hash="other") for r in rows], "manifest says"),
        (lambda rows: [dict(r, E1=object()) for r in rows], "Parquet"),
        (lambda rows: [], "missing"),
    ],
)
def test_write_table_rejects_bad_rows_and_keeps_old_file(tmp_path: Path, mutate, match) -> None:
    path = tmp_path / "results.parquet"
    good = write_table(_rows(), path, manifest=_manifest())
    before = path.read_bytes()
    with pytest.raises(StoreError, match=match):
        write_table(mutate(_rows()), path, manifest=_manifest())
    assert path.read_bytes() == before
    assert _leftovers(tmp_path) == [] and good == path


def test_write_table_interrupted_by_pyarrow_keeps_old_file(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "results.parquet"
    write_table(_rows(), path, manifest=_manifest())
    before = path.read_bytes()
    real = pq.write_table

    def half_then_crash(table, where, **kwargs):
        real(table, where, **kwargs)
        with open(where, "r+b") as handle:  # truncate to half, then fail like a full disk
            handle.truncate(os.path.getsize(where) // 2)
        raise OSError("No space left on device")

    monkeypatch.setattr(pq, "write_table", half_then_crash)
    with pytest.raises(StoreError, match="No space left"):
        write_table(_rows(offset=1.0), path, manifest=_manifest())
    assert path.read_bytes() == before
    assert _leftovers(tmp_path) == []


def test_errors_are_typed() -> None:
    assert issubclass(StoreError, LfdError) and issubclass(PartialSweepWarning, UserWarning)
    with pytest.raises(StoreError, match="cannot read"):
        read_table("/nonexistent/results.parquet")
    with pytest.raises(StoreError, match="DataFrame"):
        write_table("not rows", "/tmp/never.parquet")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------- collect


def _fake_sweep(root: Path) -> tuple[Path, pd.DataFrame]:
    """Two jobs, a duplicated part, a conflicting rerun, a stray temp file and a truncated part."""
    sweep = root / "multirun" / "2024-05-21" / "10-00-00"
    job0 = write_table(_rows(seed=0, methods=("SEDS",)), sweep / "0" / "results.parquet", manifest=_manifest(0))
    job1 = write_table(_rows(seed=1, methods=("LPV-DS",)), sweep / "1" / "results.parquet", manifest=_manifest(1))
    # The same part copied into another job folder (e.g. a re-collected output): exact duplicate rows.
    (sweep / "2").mkdir()
    shutil.copy2(job0, sweep / "2" / "results.parquet")
    # A rerun of job 1 whose first trajectory changed; written last, but in a folder that sorts first,
    # so only its write time can make it win.
    rerun_rows = _rows(seed=1, methods=("LPV-DS",))
    rerun_rows[0]["E1"] = 123.0
    write_table(rerun_rows, sweep / "00-rerun" / "results.parquet", manifest=_manifest(1))
    # A job killed while writing: its atomic temp file, and a truncated file from a non-atomic writer.
    (sweep / "3").mkdir()
    (sweep / "3" / ".results.parquet.999.abc.tmp").write_bytes(job0.read_bytes()[:100])
    (sweep / "3" / "results.parquet.tmp").write_bytes(b"PAR1")
    (sweep / "4").mkdir()
    blob = job1.read_bytes()
    (sweep / "4" / "results.parquet").write_bytes(blob[: len(blob) // 2])

    expected = pd.concat([read_table(job0), read_table(job1)], ignore_index=True)
    expected.loc[(expected["method"] == "LPV-DS") & (expected["trajectory"] == 0), "E1"] = 123.0
    expected = expected.sort_values(list(KEY_COLUMNS)).reset_index(drop=True)
    expected = expected[list(KEY_COLUMNS) + [c for c in expected.columns if c not in KEY_COLUMNS]]
    return sweep, expected


def test_collect_refuses_keys_shared_by_different_configurations(tmp_path: Path) -> None:
    # A sweep over a setting that is not part of the key (e.g. a window size missing from the method name):
    # the two jobs are different runs, not re-writes, and dropping one silently would lose half the sweep.
    sweep = tmp_path / "sweep"
    write_table(_rows(seed=0), sweep / "0" / "results.parquet", manifest=_manifest(0, {"seed": 0, "window": 5}))
    write_table(_rows(seed=0, offset=1.0), sweep / "1" / "results.parquet",
                manifest=_manifest(0, {"seed": 0, "window": 15}))  # fmt: skip
    with pytest.raises(StoreError, match="different configurations"):
        collect(sweep)


def test_collect_keeps_the_most_recent_write_after_a_revert(tmp_path: Path) -> None:
    """The same job written three times, A then B then A again (a setting changed and changed back): the merged
    table holds A, the last write, even though A's rows equal the first write's."""
    sweep = tmp_path / "sweep"
    for part, offset in enumerate((0.0, 1.0, 0.0)):
        write_table(_rows(seed=0, offset=offset), sweep / str(part) / "results.parquet", manifest=_manifest(0))
    with pytest.warns(PartialSweepWarning, match="most recent write"):
        merged = collect(sweep)
    expected = pd.DataFrame(_rows(seed=0, offset=0.0)).sort_values(list(KEY_COLUMNS))
    got = merged.sort_values(list(KEY_COLUMNS))
    assert len(got) == len(expected)
    np.testing.assert_array_equal(got["E1"].to_numpy(), expected["E1"].to_numpy())


def test_collect_merges_a_half_finished_sweep(tmp_path: Path) -> None:
    sweep, expected = _fake_sweep(tmp_path)
    with pytest.warns(PartialSweepWarning) as record:
        merged = collect(sweep)
    messages = [str(w.message) for w in record]
    assert any("skipping" in m and str(Path("4") / "results.parquet") in m for m in messages)
    assert any("kept the most recent write" in m for m in messages)
    assert not any(".tmp" in m for m in messages)  # temp files are ignored silently
    assert not merged.duplicated(subset=list(KEY_COLUMNS)).any()
    assert len(merged) == 6
    pd.testing.assert_frame_equal(merged, expected, check_dtype=False)
    assert set(PROVENANCE_COLUMNS) <= set(merged.columns)
    assert list(merged["seed"]) == [1, 1, 1, 0, 0, 0]  # sorted by key: LPV-DS before SEDS


def test_collect_is_deterministic_and_saves_atomically(tmp_path: Path) -> None:
    sweep, expected = _fake_sweep(tmp_path)
    out_dir = sweep / "merged"  # inside the sweep: must not be read back as a part
    with pytest.warns(PartialSweepWarning):
        first = collect(sweep, save_to=[out_dir / "all.parquet", out_dir / "all.csv"])
    with pytest.warns(PartialSweepWarning):
        second = collect(sweep, save_to=out_dir / "all.parquet")
    pd.testing.assert_frame_equal(first, second)
    pd.testing.assert_frame_equal(read_table(out_dir / "all.parquet"), first)
    pd.testing.assert_frame_equal(pd.read_csv(out_dir / "all.csv"), first, check_dtype=False)
    assert _leftovers(out_dir) == []
    with pytest.raises(StoreError, match="suffix"):
        collect(sweep, save_to=tmp_path / "x.xlsx")


def test_collect_edge_cases(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="no such"):
        collect(tmp_path / "missing")
    with pytest.warns(PartialSweepWarning, match="no results tables"):
        empty = collect(tmp_path)
    assert empty.empty and list(empty.columns[: len(KEY_COLUMNS)]) == list(KEY_COLUMNS)
    # A single file is accepted; a parquet that is not a results table is skipped with a warning.
    single = write_table(_rows(), tmp_path / "one" / "results.parquet", manifest=_manifest())
    alone = collect(single)
    expected = read_table(single).sort_values(list(KEY_COLUMNS)).reset_index(drop=True)
    pd.testing.assert_frame_equal(alone, expected[alone.columns])
    pq.write_table(pa.table({"a": [1, 2]}), tmp_path / "one" / "other.parquet")
    with pytest.warns(PartialSweepWarning, match="missing required"):
        assert len(collect(tmp_path / "one")) == len(_rows())


def test_collect_unions_columns_across_parts(tmp_path: Path) -> None:
    a = _rows(seed=0, methods=("SEDS",))
    b = [dict(r, DTWD=1.5) for r in _rows(seed=1, methods=("LPV-DS",))]
    write_table(a, tmp_path / "0" / "results.parquet", manifest=_manifest(0))
    write_table(b, tmp_path / "1" / "results.parquet", manifest=_manifest(1))
    merged = collect(tmp_path)
    assert merged.loc[merged["method"] == "LPV-DS", "DTWD"].eq(1.5).all()
    assert merged.loc[merged["method"] == "SEDS", "DTWD"].isna().all()


def test_collect_rejects_key_columns_with_mixed_types(tmp_path: Path) -> None:
    write_table(_rows(seed=0), tmp_path / "0" / "results.parquet", manifest=_manifest(0))
    as_text = [dict(r, trajectory=f"demo{r['trajectory']}") for r in _rows(seed=1)]
    write_table(as_text, tmp_path / "1" / "results.parquet", manifest=_manifest(1))
    with pytest.raises(StoreError, match="mixes types"):
        collect(tmp_path)


def test_collect_cli(tmp_path: Path, capsys) -> None:
    sweep, expected = _fake_sweep(tmp_path)
    out = tmp_path / "merged.parquet"
    done = subprocess.run(
        [sys.executable, "-W", "error::RuntimeWarning", "-m", "lfd_torch.store.collect", str(sweep), "--out", str(out)],
        capture_output=True, text=True, cwd=tmp_path, timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr
    assert "6 rows" in done.stderr and "skipping" in done.stderr
    pd.testing.assert_frame_equal(read_table(out), expected, check_dtype=False)
    # In-process, printing CSV to stdout; a missing directory is exit status 2.
    assert collect_main([str(sweep)]) == 0
    printed = capsys.readouterr().out
    pd.testing.assert_frame_equal(pd.read_csv(__import__("io").StringIO(printed)), expected, check_dtype=False)
    assert collect_main([str(tmp_path / "missing")]) == 2


def test_next_save_removes_temporaries_of_killed_writers(tmp_path):
    import os
    import subprocess
    import sys

    from lfd_torch.store import atomic_write

    target = tmp_path / "table.parquet"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    stale = tmp_path / f".table.parquet.{dead_pid}.0123abcd.tmp"
    stale.write_bytes(b"half")
    live = tmp_path / f".table.parquet.{os.getppid()}.4567ef.tmp"  # a live process: a concurrent writer, kept
    live.write_bytes(b"in progress")
    other = tmp_path / f".other.parquet.{dead_pid}.89ab.tmp"  # another destination: not ours to clean
    other.write_bytes(b"x")
    atomic_write(target, lambda p: p.write_bytes(b"new"))
    assert target.read_bytes() == b"new"
    assert not stale.exists() and live.exists() and other.exists()


def test_prepare_job_checks_the_seed_and_resolves_the_folder(tmp_path):
    from omegaconf import OmegaConf

    from lfd_torch.errors import InvalidArgumentError
    from lfd_torch.store import prepare_job

    job = prepare_job(OmegaConf.create({"seed": 3, "out_dir": str(tmp_path), "x": 1}))
    assert job.out_dir == tmp_path and job.manifest["seed"] == 3 and not job.multirun
    for bad in ("3", 2.0, True, None):
        with pytest.raises(InvalidArgumentError, match="seed"):
            prepare_job(OmegaConf.create({"seed": bad}))


def test_published_paths_do_not_depend_on_the_working_directory(tmp_path, monkeypatch):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import lfd_torch
    from lfd_torch.store.paths import project_root

    conf = Path(lfd_torch.__file__).resolve().parents[1] / "conf"
    monkeypatch.delenv("LFD_ROOT", raising=False)
    monkeypatch.chdir(tmp_path)
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("lasa_tasks")
    tables = Path(OmegaConf.to_container(cfg.paths, resolve=True)["tables"])
    assert tables == conf.parent / "results" / "tables" and tables.is_absolute()
    monkeypatch.setenv("LFD_ROOT", str(tmp_path / "elsewhere"))
    assert project_root() == str((tmp_path / "elsewhere").resolve())


def test_collect_refuses_to_publish_a_partial_sweep(tmp_path):
    from lfd_torch.store import write_table
    from lfd_torch.store.sweep import main as collect_main, unfinished_jobs

    sweep = tmp_path / "sweep"
    for job in ("0", "1"):
        (sweep / job / ".hydra").mkdir(parents=True)
        (sweep / job / ".hydra" / "config.yaml").write_text("seed: 0\n")
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "config_hash": "h",
           "package_version": "v", "git_sha": "g", "x": 1.0}  # fmt: skip
    write_table([row], sweep / "0" / "results.parquet")
    assert unfinished_jobs(sweep) == [sweep / "1"]
    assert collect_main([str(sweep), "--out", str(tmp_path / "t.parquet")]) == 2 and not (tmp_path / "t.parquet").exists()
    assert collect_main([str(sweep), "--out", str(tmp_path / "t.parquet"), "--force"]) == 0
    write_table([{**row, "trajectory": 1}], sweep / "1" / "results.parquet")
    assert unfinished_jobs(sweep) == []
    assert collect_main([str(sweep), "--out", str(tmp_path / "t2.parquet")]) == 0


def _multirun_yaml(sweep, task):
    """A sweep's multirun.yaml as Hydra's basic sweeper writes it (only the keys ``expected_jobs`` reads)."""
    sweep.mkdir(parents=True, exist_ok=True)
    (sweep / "multirun.yaml").write_text(
        "hydra:\n  sweep:\n    subdir: ${hydra.job.num}\n"
        "  sweeper:\n    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n"
        "    params:\n      shape: a,b\n  overrides:\n    task:\n" + "".join(f"    - {t}\n" for t in task))


def test_jobs_that_never_started_keep_a_sweep_unfinished(tmp_path):
    """A sweep killed before some jobs made a folder: its multirun.yaml says how many jobs it launches (command-line
    sweeps times the preset's sweeper params), so collect --out refuses it and report_benchmark would too."""
    from lfd_torch.store import write_table
    from lfd_torch.store.sweep import expected_jobs, main as collect_main, unfinished_jobs

    sweep = tmp_path / "sweep"
    _multirun_yaml(sweep, ["fold=0,1,2", "budget_s=5"])
    assert expected_jobs(sweep / "multirun.yaml") == 6  # 3 folds x 2 shapes
    (sweep / "0" / ".hydra").mkdir(parents=True)
    (sweep / "0" / ".hydra" / "config.yaml").write_text("seed: 0\n")
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "config_hash": "h",
           "package_version": "v", "git_sha": "g", "x": 1.0}  # fmt: skip
    write_table([row], sweep / "0" / "results.parquet")
    assert unfinished_jobs(sweep) == [sweep / str(k) for k in range(1, 6)]
    assert collect_main([str(sweep), "--out", str(tmp_path / "t.parquet")]) == 2 and not (tmp_path / "t.parquet").exists()
    _multirun_yaml(sweep, ["shape=a", "budget_s=5"])  # the command line overrides the preset's params: one job
    assert expected_jobs(sweep / "multirun.yaml") == 1 and unfinished_jobs(sweep) == []
    text = (sweep / "multirun.yaml").read_text().replace("${hydra.job.num}", "${hydra.job.override_dirname}")
    (sweep / "multirun.yaml").write_text(text)  # job folders named otherwise: the count is not used
    assert expected_jobs(sweep / "multirun.yaml") is None


def test_a_published_table_is_never_replaced_by_an_empty_or_mixed_collect(tmp_path):
    from lfd_torch.store import write_table

    published = tmp_path / "published.parquet"
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "config_hash": "h",
           "package_version": "v", "git_sha": "g", "x": 1.0}  # fmt: skip
    write_table([row], published)
    before = published.read_bytes()
    (tmp_path / "empty_sweep").mkdir()
    with pytest.raises(StoreError, match="nothing written"):
        collect(tmp_path / "empty_sweep", save_to=published)
    root = tmp_path / "multirun" / "lasa_benchmark"
    for stamp in ("2026-01-01_10-00-00", "2026-01-02_10-00-00"):  # two unrelated runs of the default sweep dir
        _multirun_yaml(root / stamp, ["fold=0"])
        write_table([row], root / stamp / "0" / "results.parquet")
    with pytest.raises(StoreError, match="holds 2 sweeps"):
        collect(root, save_to=published)
    assert published.read_bytes() == before
    assert len(collect(root / "2026-01-01_10-00-00", save_to=published)) == 1


def test_staged_outputs_publish_together_or_not_at_all(tmp_path):
    """A run's outputs are staged under results/ and replace the published ones only when it succeeds; a failure
    halfway leaves every published file as it was, and no staging folder."""
    from omegaconf import OmegaConf

    from lfd_torch.store import staged_outputs, staged_results

    results = tmp_path / "results"
    (results / "tables").mkdir(parents=True)
    (results / "figures").mkdir()
    (results / "tables" / "t.md").write_text("old table\n")
    (results / "figures" / "f.png").write_text("old figure\n")
    with pytest.raises(RuntimeError, match="killed halfway"):
        with staged_outputs(results) as staging:
            (staging / "figures").mkdir()
            (staging / "figures" / "f.png").write_text("new figure\n")  # written before the failure
            raise RuntimeError("killed halfway")
    assert (results / "figures" / "f.png").read_text() == "old figure\n"
    assert not list(results.glob(".staging-*"))
    cfg = OmegaConf.create({"publish": True, "paths": {"root": str(tmp_path), "results": "${paths.root}/results",
                                                       "tables": "${paths.results}/tables",
                                                       "figures": "${paths.results}/figures"}})
    with staged_results(cfg) as final:
        staged_table = Path(cfg.paths.tables) / "t.md"
        assert staged_table.parent.parent.name.startswith(".staging-")
        staged_table.parent.mkdir(parents=True)
        staged_table.write_text("new table\n")
        assert (results / "tables" / "t.md").read_text() == "old table\n"  # not yet
    assert (results / "tables" / "t.md").read_text() == "new table\n" and final(staged_table) == results / "tables" / "t.md"
    assert cfg.paths.tables == str(results / "tables") and not list(results.glob(".staging-*"))
    off = OmegaConf.create({"publish": False, "paths": {"results": str(results)}})
    with staged_results(off) as final:
        assert cfg.paths.results == str(results) and final("x") == Path("x")


def test_report_benchmark_refuses_an_empty_sweep_and_keeps_the_published_table(tmp_path, monkeypatch, capsys):
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    from report_benchmark import main as report

    monkeypatch.setenv("LFD_ROOT", str(tmp_path))
    published = tmp_path / "results" / "tables" / "paper.parquet"
    published.parent.mkdir(parents=True)
    published.write_bytes(b"the published table")
    (tmp_path / "empty_sweep").mkdir()
    assert report([str(tmp_path / "empty_sweep"), "--name", "paper"]) == 2
    assert published.read_bytes() == b"the published table" and "nothing" in capsys.readouterr().err


def test_a_part_from_another_commit_is_not_resumed(tmp_path):
    """Resuming a sweep reuses a job's rows only when they come from the same configuration, seed and commit."""
    from lfd_torch.store import finished_part, write_table

    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0, "config_hash": "h",
           "package_version": "v", "git_sha": "g1", "x": 1.0}  # fmt: skip
    manifest = {"config_hash": "h", "seed": 0, "git_sha": "g1", "package_version": "v"}
    write_table([row], tmp_path / "results.parquet", manifest=manifest)
    assert finished_part(tmp_path / "results.parquet", manifest) is not None
    for change in ({"git_sha": "g2"}, {"config_hash": "h2"}, {"seed": 1}):
        assert finished_part(tmp_path / "results.parquet", {**manifest, **change}) is None
