"""Sweeps that must not be published as they are: a damaged job file, rows an earlier sweep into the same folder left
behind, job folders beyond the sweep's job count, damaged pandas metadata, and a seed outside int64.

The README's promise is checked throughout: a partial sweep never overwrites a published table. Sweep folders are
laid out by hand as Hydra writes them (``multirun.yaml``, ``<job>/.hydra/config.yaml``, ``<job>/results.parquet``
written with the job's run manifest), so no experiment runs.
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
from omegaconf import OmegaConf

from lfd_torch.errors import InvalidArgumentError, StoreError
from lfd_torch.store import (
    PartialSweepWarning,
    collect,
    config_hash,
    find_parts,
    finished_part,
    prepare_job,
    read_table,
    unfinished_jobs,
    write_table,
)
from lfd_torch.store.sweep import main as collect_main

REPO_ROOT = Path(__file__).resolve().parents[1]
METRICS = {"E1": 1.0, "E2": 0.1, "E3": 2.0, "DTWD": 3.0, "final_error": 0.01}


def _job_cfg(fold: int, budget_s: float = 2.0, seed: int = 0) -> dict:
    return {"experiment": "lasa_benchmark", "seed": seed, "fold": fold, "budget_s": budget_s, "progress": False}


def _manifest(cfg: dict) -> dict:
    """What prepare_job stores with a job's rows: config_hash of the job's configuration, and its seed."""
    return {"config_hash": config_hash(cfg), "seed": cfg["seed"], "package_version": "v", "git_sha": "g"}


def _rows(cfg: dict) -> list[dict]:
    """A lasa_benchmark-like part: one train and one test row of fold ``cfg['fold']``."""
    return [{"experiment": cfg["experiment"], "shape": "Angle", "method": "none+lpvds+none", "fold": cfg["fold"],
             "seed": cfg["seed"], "trajectory": t, "split": split, "status": "ok", "reached": True, **METRICS}
            for t, split in ((cfg["fold"], "train"), (cfg["fold"] + 1, "test"))]  # fmt: skip


def _write_job(sweep: Path, job: int, cfg: dict, rows_cfg: dict | None = None) -> Path:
    """Job folder ``sweep/job`` of configuration ``cfg`` (its .hydra/config.yaml) holding the rows of ``rows_cfg``
    (default: ``cfg``, a finished job; another one: rows an earlier sweep into the same folder left there)."""
    folder = sweep / str(job)
    (folder / ".hydra").mkdir(parents=True, exist_ok=True)
    OmegaConf.save(OmegaConf.create(cfg), folder / ".hydra" / "config.yaml")
    rows_cfg = cfg if rows_cfg is None else rows_cfg
    return write_table(_rows(rows_cfg), folder / "results.parquet", manifest=_manifest(rows_cfg))


def _multirun_yaml(sweep: Path, task: list[str]) -> None:
    """The keys of multirun.yaml that expected_jobs reads, as Hydra's basic sweeper writes them."""
    sweep.mkdir(parents=True, exist_ok=True)
    (sweep / "multirun.yaml").write_text(
        "hydra:\n  sweep:\n    subdir: ${hydra.job.num}\n"
        "  sweeper:\n    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n    params: null\n"
        "  overrides:\n    task:\n" + "".join(f"    - {t}\n" for t in task))


def _two_fold_sweep(tmp_path: Path) -> Path:
    """`lasa_benchmark.py -m fold=0,1 hydra.sweep.dir=S`, both jobs finished."""
    sweep = tmp_path / "S"
    _multirun_yaml(sweep, ["fold=0,1", "budget_s=2"])
    for fold in (0, 1):
        _write_job(sweep, fold, _job_cfg(fold))
    return sweep


def _truncate_to_200_bytes(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:200])


def _pandas_metadata(change):
    def damage(path: Path) -> None:
        table = pq.read_table(path)
        meta = dict(table.schema.metadata)
        meta[b"pandas"] = change(meta[b"pandas"])
        pq.write_table(table.replace_schema_metadata(meta), path)

    return damage


def _edit_json(edit):
    def change(raw: bytes) -> bytes:
        doc = json.loads(raw)
        edit(doc)
        return json.dumps(doc).encode()

    return change


def _drop_index_columns(doc: dict) -> None:
    del doc["index_columns"]


def _unknown_numpy_type(doc: dict) -> None:
    next(c for c in doc["columns"] if c["name"] == "fold")["numpy_type"] = "inT64"


def _drop_numpy_type(doc: dict) -> None:
    del next(c for c in doc["columns"] if c["name"] == "fold")["numpy_type"]


def _columns_not_a_list(doc: dict) -> None:
    doc["columns"] = 5


DAMAGED_PANDAS_METADATA = {  # what random bit flips in the 'pandas' metadata gave: each escaped as a raw error
    "broken JSON '{' (JSONDecodeError)": _pandas_metadata(lambda raw: b"{"),
    "not UTF-8 (UnicodeDecodeError)": _pandas_metadata(lambda raw: b"\xff\xfe" + raw[2:]),
    "no index_columns (KeyError)": _pandas_metadata(_edit_json(_drop_index_columns)),
    "no numpy_type (KeyError)": _pandas_metadata(_edit_json(_drop_numpy_type)),
    "dtype 'inT64' (TypeError)": _pandas_metadata(_edit_json(_unknown_numpy_type)),
    "columns not a list (TypeError)": _pandas_metadata(_edit_json(_columns_not_a_list)),
}
DAMAGES = {"truncated to 200 bytes": _truncate_to_200_bytes, **DAMAGED_PANDAS_METADATA}


def _publish(sweep: Path, published: Path) -> bytes:
    """The full sweep, published: its bytes (what a refused publish must leave)."""
    assert collect_main([str(sweep), "--out", str(published)]) == 0
    assert sorted(read_table(published)["fold"].unique()) == [0, 1]
    return published.read_bytes()


# ------------------------------------------------------------------------------------ 1. a damaged job file
@pytest.mark.parametrize("damage", list(DAMAGES.values()), ids=list(DAMAGES))
def test_a_damaged_job_file_leaves_its_job_unfinished_and_the_published_table_as_it_was(tmp_path, damage, capsys):
    """Property: a job whose only results file cannot be read is unfinished (unfinished_jobs names it), so
    `collect --out` exits 2 and writes nothing, as for a job that wrote no file; `--force` still publishes the rest
    with a warning. Before: any existing *.parquet counted as finished, and the published 14-row table was replaced by
    the readable half (exit 0, only a warning)."""
    sweep = _two_fold_sweep(tmp_path)
    published = tmp_path / "pub.parquet"
    before = _publish(sweep, published)
    damage(sweep / "1" / "results.parquet")
    assert unfinished_jobs(sweep) == [sweep / "1"]
    capsys.readouterr()
    assert collect_main([str(sweep), "--out", str(published)]) == 2
    assert published.read_bytes() == before
    err = capsys.readouterr().err
    assert "1 job(s)" in err and str(sweep / "1") in err
    forced = tmp_path / "forced.parquet"
    assert collect_main([str(sweep), "--out", str(forced), "--force"]) == 0
    assert read_table(forced)["fold"].unique().tolist() == [0]
    assert "skipping" in capsys.readouterr().err


@pytest.fixture
def report_benchmark(tmp_path, monkeypatch):
    """experiments/report_benchmark.py's main, publishing into tmp_path/results."""
    monkeypatch.setenv("LFD_ROOT", str(tmp_path))
    monkeypatch.syspath_prepend(str(REPO_ROOT / "experiments"))
    sys.modules.pop("report_benchmark", None)
    from report_benchmark import main

    return main


def test_report_benchmark_refuses_a_sweep_with_a_damaged_job_file_and_reports_skipped_parts(
    tmp_path, report_benchmark, capsys
):
    """Property: report_benchmark exits 2 and leaves the published table, summary and violins as they were when a job
    file is damaged; with --force it publishes the readable jobs and prints the skipped part on stderr. Before: exit
    0, the 14-row table replaced by 7 rows, and no warning (PartialSweepWarning was ignored)."""
    sweep = _two_fold_sweep(tmp_path)
    assert report_benchmark([str(sweep), "--name", "rb"]) == 0
    tables = tmp_path / "results" / "tables"
    published = {p: p.read_bytes() for p in tables.iterdir()}
    assert sorted(read_table(tables / "rb.parquet")["fold"].unique()) == [0, 1]
    _truncate_to_200_bytes(sweep / "1" / "results.parquet")
    capsys.readouterr()
    assert report_benchmark([str(sweep), "--name", "rb"]) == 2
    assert {p: p.read_bytes() for p in tables.iterdir()} == published
    assert str(sweep / "1") in capsys.readouterr().err
    assert report_benchmark([str(sweep), "--name", "forced", "--force"]) == 0
    err = capsys.readouterr().err
    assert "warning: skipping sweep part" in err and str(sweep / "1" / "results.parquet") in err
    assert read_table(tables / "forced.parquet")["fold"].unique().tolist() == [0]


# ------------------------------------------------------------------------------------ 2. rows of an older configuration
def test_rows_of_another_configuration_do_not_finish_a_job(tmp_path, capsys):
    """Property: a part whose run manifest has another config_hash than its job's .hydra/config.yaml (the sweep was
    re-run into the same folder with budget_s=3 fold=0,9; job 1 failed and its budget_s=2 fold=1 rows survived) is
    skipped by collect with a warning naming both hashes, its job is unfinished, and `collect --out` exits 2 writing
    nothing. Before: exit 0, with configurations dc72.. and 6fc4.. mixed in one table."""
    sweep = _two_fold_sweep(tmp_path)
    published = tmp_path / "pub.parquet"
    before = _publish(sweep, published)
    _multirun_yaml(sweep, ["budget_s=3", "fold=0,9"])
    _write_job(sweep, 0, _job_cfg(0, budget_s=3))  # job 0 re-ran: its rows are of the new configuration
    _write_job(sweep, 1, _job_cfg(9, budget_s=3), rows_cfg=_job_cfg(1, budget_s=2))  # job 1 failed: old rows
    old_hash, new_hash = config_hash(_job_cfg(1, budget_s=2)), config_hash(_job_cfg(9, budget_s=3))
    assert unfinished_jobs(sweep) == [sweep / "1"]
    with pytest.warns(PartialSweepWarning, match="another configuration") as record:
        merged = collect(sweep)
    assert any(old_hash in str(w.message) and new_hash in str(w.message) for w in record)
    assert merged["config_hash"].unique().tolist() == [config_hash(_job_cfg(0, budget_s=3))]
    capsys.readouterr()
    assert collect_main([str(sweep), "--out", str(published)]) == 2
    assert published.read_bytes() == before


def test_rows_of_another_seed_do_not_finish_a_job(tmp_path):
    """Property: the seed is checked too (config_hash leaves it out): a job folder re-run with seed=1 that still
    holds seed-0 rows is unfinished. Before: the seed-0 rows counted as the seed-1 job's."""
    sweep = tmp_path / "S"
    _multirun_yaml(sweep, ["seed=1", "fold=0,1"])
    _write_job(sweep, 0, _job_cfg(0, seed=1))
    _write_job(sweep, 1, _job_cfg(1, seed=1), rows_cfg=_job_cfg(1, seed=0))
    assert unfinished_jobs(sweep) == [sweep / "1"]
    with pytest.warns(PartialSweepWarning, match="another configuration"):
        assert collect(sweep)["seed"].unique().tolist() == [1]


def test_job_folders_beyond_the_sweep_job_count_are_not_merged(tmp_path, capsys):
    """Property: after `-m fold=0` (1 job) into the folder of an earlier `-m fold=0,1` sweep, the leftover folder 1/
    is not a job of the sweep: collect ignores it (with a warning), unfinished_jobs does not list it even when it
    holds no rows, and the published table holds fold 0 only. Before: folder 1's rows were merged."""
    sweep = _two_fold_sweep(tmp_path)
    _multirun_yaml(sweep, ["fold=0", "budget_s=2"])
    with pytest.warns(PartialSweepWarning, match="ignoring"):
        merged = collect(sweep)
    assert merged["fold"].unique().tolist() == [0]
    assert unfinished_jobs(sweep) == []
    published = tmp_path / "pub.parquet"
    assert collect_main([str(sweep), "--out", str(published)]) == 0
    assert read_table(published)["fold"].unique().tolist() == [0]
    (sweep / "1" / "results.parquet").unlink()  # a leftover job folder without rows does not block publishing
    assert unfinished_jobs(sweep) == []


def _prepare(out_dir: Path, **cfg):
    return prepare_job(OmegaConf.create({**_job_cfg(0), "out_dir": str(out_dir), **cfg}))


@pytest.mark.parametrize("earlier", [{"budget_s": 3.0}, {"seed": 1}], ids=["another config", "another seed"])
def test_prepare_job_sets_aside_results_of_another_configuration(tmp_path, earlier):
    """Property: prepare_job moves an existing results.parquet of another configuration (or seed) aside before the
    job runs, keeping its bytes in a file that is no part of the sweep, so a job that then fails leaves no stale rows
    in its folder. Before: the old file stayed and was collected as the job's rows."""
    old_cfg = {**_job_cfg(0), **earlier}
    path = write_table(_rows(old_cfg), tmp_path / "results.parquet", manifest=_manifest(old_cfg))
    data = path.read_bytes()
    job = _prepare(tmp_path)
    assert not path.exists()
    assert job.set_aside is not None and job.set_aside.parent == tmp_path and job.set_aside.read_bytes() == data
    assert find_parts(tmp_path) == []


def test_prepare_job_keeps_results_of_its_own_configuration(tmp_path):
    """Property (the control of the test above): rows of the job's own configuration and seed stay in place for
    resuming (finished_part reads them), and nothing is set aside."""
    cfg = OmegaConf.create({**_job_cfg(0), "out_dir": str(tmp_path)})
    job = prepare_job(cfg)
    path = write_table(_rows(_job_cfg(0)), tmp_path / "results.parquet", manifest=job.manifest)
    again = prepare_job(cfg)
    assert again.set_aside is None and path.is_file()
    assert finished_part(path, again.manifest) is not None


# ------------------------------------------------------------------------------------ 3. damaged pandas metadata
@pytest.mark.parametrize("damage", list(DAMAGED_PANDAS_METADATA.values()), ids=list(DAMAGED_PANDAS_METADATA))
def test_damaged_pandas_metadata_is_a_store_error_a_skipped_part_and_an_unfinished_job(tmp_path, damage):
    """Property: a results file whose 'pandas' schema metadata is damaged makes read_table raise StoreError naming the
    file, collect skip the part with a PartialSweepWarning (keeping the other job's rows), and finished_part return
    None (the job re-runs, as its docstring says). Before: JSONDecodeError, UnicodeDecodeError, KeyError or TypeError
    escaped from all three."""
    sweep = _two_fold_sweep(tmp_path)
    part = sweep / "0" / "results.parquet"
    damage(part)
    with pytest.raises(StoreError, match="results.parquet"):
        read_table(part)
    with pytest.warns(PartialSweepWarning, match="skipping sweep part"):
        merged = collect(sweep)
    assert merged["fold"].unique().tolist() == [1]
    assert finished_part(part, _manifest(_job_cfg(0))) is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PartialSweepWarning)
        with pytest.raises(StoreError, match="nothing written"):
            collect(part, save_to=tmp_path / "out.parquet")  # the only part unreadable: nothing is written
    assert not (tmp_path / "out.parquet").exists()


# ------------------------------------------------------------------------------------ 4. a seed outside int64
@pytest.mark.parametrize("seed", [2**63, -(2**63) - 1, 99999999999999999999999])
def test_prepare_job_rejects_a_seed_outside_int64(tmp_path, seed):
    """Property: a seed that the int64 seed column cannot hold is refused up front with InvalidArgumentError naming
    seed (before: OverflowError from pyarrow when the rows were written, after the whole run); the int64 bounds
    themselves are accepted."""
    with pytest.raises(InvalidArgumentError, match="seed"):
        _prepare(tmp_path, seed=seed)
    for bound in (2**63 - 1, -(2**63)):
        assert _prepare(tmp_path, seed=bound).manifest["seed"] == bound
    top = {**_job_cfg(0), "seed": 2**63 - 1}  # and a table stores it
    assert read_table(write_table(pd.DataFrame(_rows(top)), tmp_path / "b.parquet", manifest=_manifest(top)))[
        "seed"].tolist() == [2**63 - 1] * 2
