"""Bad input to lfd_torch.gmm, lfd_torch.viz and lfd_torch.store: a typed lfd_torch error naming the argument, never a
deep crash or a silent wrong result, and nothing already written lost or half-written."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
import pytest
import torch

from lfd_torch import gmm as G
from lfd_torch.errors import (
    InvalidArgumentError,
    InvalidGMMError,
    NonFiniteError,
    PlotError,
    ShapeMismatchError,
    StoreError,
    TooFewSamplesError,
    UnknownNameError,
)

F = torch.float64
NAN = math.nan


@pytest.fixture()
def x() -> torch.Tensor:
    return torch.randn(50, 2, dtype=F, generator=torch.Generator().manual_seed(0))


@pytest.fixture()
def gm(x) -> G.GMM:
    return G.GMM.from_labels(x, (x[:, 0] > 0).long())


def _gen() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def _prior(**kw) -> G.NIWPrior:
    f = dict(mean=torch.zeros(2, dtype=F), kappa=torch.tensor(1.0, dtype=F), dof=torch.tensor(4.0, dtype=F),
             scale=torch.eye(2, dtype=F))  # fmt: skip
    f.update(kw)
    return G.NIWPrior(**f)


# ============================================================================================ 1. merge_small_components
def test_merge_small_components_checks_its_arguments(x) -> None:
    lab = torch.zeros(50, dtype=torch.long)
    for bad in (NAN, 0, 1.5):
        with pytest.raises(InvalidArgumentError, match="min_size"):
            G.merge_small_components(x, lab, bad)
    with pytest.raises(NonFiniteError, match="x"):
        G.merge_small_components(x * NAN, lab, 1)
    with pytest.raises(ShapeMismatchError, match="labels"):
        G.merge_small_components(x, lab.double(), 1)
    with pytest.raises(InvalidArgumentError, match="labels must be >= 0"):
        G.merge_small_components(x, lab - 1, 1)
    with pytest.raises(ShapeMismatchError, match="labels"):
        G.merge_small_components(x, lab[:3], 1)
    with pytest.raises(TooFewSamplesError, match="x"):
        G.merge_small_components(x[:0], lab[:0], 1)
    with pytest.raises(ShapeMismatchError, match="x"):
        G.merge_small_components(x[:, 0], lab, 1)
    # valid input unchanged
    xs = torch.tensor([[0.0], [0.1], [0.2], [10.0], [10.1], [10.2], [9.0], [0.5]], dtype=F)
    assert G.merge_small_components(xs, torch.tensor([0, 0, 0, 1, 1, 1, 2, 3]), 2).tolist() == [0, 0, 0, 1, 1, 1, 1, 0]


# ============================================================================================ 2. regularize / order
def test_regularize_covariances_and_order_by_attractor_name_their_arguments(gm) -> None:
    for bad in ("abc", None, NAN):
        with pytest.raises(InvalidGMMError, match="min_eig_ratio"):
            G.regularize_covariances(gm, bad)
    with pytest.raises(InvalidGMMError, match="min_eig must"):
        G.regularize_covariances(gm, min_eig=math.inf)
    for bad in ("ab", None):
        with pytest.raises(ShapeMismatchError, match="attractor"):
            G.order_by_attractor(gm, bad)
    assert G.order_by_attractor(gm, [0.0, 0.0]).n_components == 2  # a list still works


# ============================================================================================ 3. NIW
def test_niw_prior_posterior_and_draws_check_their_arguments(x) -> None:
    with pytest.raises(NonFiniteError, match="x"):
        G.niw_prior_from_data(x * NAN)
    with pytest.raises(InvalidArgumentError, match="covariance_scale"):
        G.niw_prior_from_data(x, covariance_scale=NAN)
    with pytest.raises(InvalidArgumentError, match="shape"):
        G.sample_gamma(torch.tensor([-1.0], dtype=F), _gen())
    with pytest.raises(InvalidArgumentError, match="shape"):
        G.sample_gamma(torch.tensor([NAN], dtype=F), _gen())
    with pytest.raises(InvalidArgumentError, match="dof"):
        _prior(dof=torch.tensor(1.0, dtype=F))
    with pytest.raises(InvalidArgumentError, match="kappa"):
        _prior(kappa=torch.tensor(0.0, dtype=F))
    with pytest.raises(InvalidArgumentError, match="counts"):
        G.niw_posterior(_prior(), torch.tensor([-3.0], dtype=F), torch.zeros(1, 2, dtype=F),
                        torch.zeros(1, 2, 2, dtype=F))  # fmt: skip
    with pytest.raises(InvalidArgumentError, match="scale must be symmetric positive definite"):  # at NIWPrior(...)
        G.sample_niw(_prior(scale=-torch.eye(2, dtype=F)), _gen())
    # valid input unchanged: Gamma(0) is the documented degenerate limit, draws reproducible
    assert float(G.sample_gamma(torch.tensor([0.0], dtype=F), _gen())[0]) == torch.finfo(F).tiny
    a = torch.tensor([0.5, 2.0, 30.0], dtype=F)
    assert torch.equal(G.sample_gamma(a, _gen()), G.sample_gamma(a, _gen()))


# ============================================================================================ 4. Gaussian kernels
def test_gaussian_kernels_raise_typed_errors(x) -> None:
    with pytest.raises(InvalidArgumentError, match="covariance"):
        G.gaussian_log_density(x, torch.zeros(2, dtype=F), torch.zeros(2, 2, dtype=F))
    with pytest.raises(torch.linalg.LinAlgError):  # still what the samplers' callers map to a SolverError
        G.gaussian_log_density(x, torch.zeros(1, 2, dtype=F), torch.zeros(1, 2, 2, dtype=F))
    with pytest.raises(ShapeMismatchError, match="dtype"):
        G.gaussian_log_density(x.float(), torch.zeros(1, 2, dtype=F), torch.eye(2, dtype=F)[None])
    with pytest.raises(InvalidGMMError, match="covariances"):
        G.GaussianBank(torch.zeros(1, 2, dtype=F), torch.zeros(1, 2, 2, dtype=F))
    with pytest.raises(NonFiniteError, match="covariances"):
        G.GaussianBank(torch.zeros(1, 2, dtype=F), torch.eye(2, dtype=F)[None] * NAN)
    bank = G.GaussianBank(torch.zeros(1, 2, dtype=F), torch.eye(2, dtype=F)[None])
    with pytest.raises(ShapeMismatchError, match="x is torch.float32"):
        bank.log_density(x.float())
    with pytest.raises(NonFiniteError, match="x"):
        bank.log_density(x * NAN)
    want = G.gaussian_log_density(x, torch.zeros(1, 2, dtype=F), torch.eye(2, dtype=F)[None])
    torch.testing.assert_close(bank.log_density(x), want)  # valid input unchanged


# ============================================================================================ 5. GMM construction
def test_gmm_from_labels_state_dict_and_replace(x, gm) -> None:
    lab = torch.zeros(50, dtype=torch.long)
    with pytest.raises(ShapeMismatchError, match="labels"):
        G.GMM.from_labels(x, [0] * 50)
    for bad, match in (("a", "reg_covar"), (-1, "reg_covar"), (NAN, "reg_covar")):
        with pytest.raises(InvalidGMMError, match=match):
            G.GMM.from_labels(x, lab, reg_covar=bad)
    with pytest.raises(StoreError, match="mapping"):
        G.GMM.from_state_dict(None)
    with pytest.raises(InvalidArgumentError, match="bogus"):
        gm.replace(bogus=1)
    assert torch.equal(gm.replace(weights=gm.weights).means, gm.means)


# ============================================================================================ 6. BIC
def test_bic_and_n_parameters_check_their_arguments(x, gm) -> None:
    with pytest.raises(TooFewSamplesError, match="x"):
        G.bic(gm, x[:0])
    with pytest.raises(InvalidArgumentError, match="n_components"):
        G.n_parameters(-1, 2)
    with pytest.raises(InvalidArgumentError, match="n_components"):
        G.n_parameters(2.5, "2")
    with pytest.raises(InvalidArgumentError, match="dim"):
        G.n_parameters(2, "2")
    with pytest.raises(InvalidArgumentError, match="n_effective"):
        G.fit_em_bic(x, k_range=[1], generator=_gen(), n_effective="3")
    with pytest.raises(InvalidArgumentError, match="n_effective"):
        G.bic(gm, x, n_effective="3")
    assert G.n_parameters(2, 2) == 11
    assert G.bic(gm, x) == pytest.approx(-2 * float(gm.log_prob(x).sum()) + 11 * math.log(50))


# ============================================================================================ 7. fitters
@pytest.mark.parametrize("make, name", [
    (lambda: G.PCGMMFitter(alpha=-1), "alpha"),
    (lambda: G.PCGMMFitter(reg_covar=NAN), "reg_covar"),
    (lambda: G.EMFitter(tol=-1), "tol"),
    (lambda: G.EMFitter(n_components=0), "n_components"),
    (lambda: G.EMBICFitter(k_range=[0, 2]), "k_range"),
    (lambda: G.DAMMFitter(kappa=NAN), "kappa"),
    (lambda: G.DAMMFitter(n_iter=0), "n_iter"),
])  # fmt: skip
def test_fitters_check_their_hyperparameters_at_construction(make, name) -> None:
    with pytest.raises(InvalidArgumentError, match=name):
        make()


# ============================================================================================ 8. stored files
def test_stored_files_check_paths_and_contents(tmp_path: Path) -> None:
    from lfd_torch.viz.stored import load_config, load_demos, load_state, save_config, save_demos, save_state

    path = save_config({"hydra": 1, "h": 2, "a": 3}, tmp_path / "c.json", drop="hydra")
    assert dict(load_config(path)) == {"h": 2, "a": 3}  # a string is one key, not its characters
    with pytest.raises(InvalidArgumentError, match="drop"):
        save_config({"a": 1}, tmp_path / "c.json", drop=3)
    with pytest.raises(StoreError, match="cfg"):
        save_config([1, 2], tmp_path / "c2.json")
    with pytest.raises(StoreError, match="demos"):
        save_demos([1], tmp_path / "d.pt")
    for load in (load_state, load_config, load_demos):
        with pytest.raises(StoreError, match="path"):
            load(None)
    with pytest.raises(StoreError, match="path"):
        save_state({"a": 1}, None)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(StoreError, match="afile"):
        save_state({"a": 1}, tmp_path / "afile" / "s.pt")
    assert not list(tmp_path.glob("c2.json")) and not list(tmp_path.glob("d.pt"))


def test_save_state_wraps_write_failures_and_keeps_the_old_file(tmp_path: Path, monkeypatch) -> None:
    from lfd_torch.viz import stored

    path = stored.save_state({"a": 1}, tmp_path / "s.pt")
    before = path.read_bytes()

    def fail(obj, f):
        Path(f).write_bytes(b"half")
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(stored.torch, "save", fail)
    with pytest.raises(StoreError, match="s.pt"):
        stored.save_state({"a": 2}, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.pt"]  # no temporary file left


# ============================================================================================ 9. violin
@pytest.fixture()
def table() -> pd.DataFrame:
    row = {"experiment": "e", "shape": "s", "fold": 0, "seed": 0, "config_hash": "h", "package_version": "v",
           "git_sha": "g"}  # fmt: skip
    return pd.DataFrame([dict(row, method=m, trajectory=i, E1=float(i)) for m in "ab" for i in range(5)])


def test_violin_rejects_orders_and_metric_columns_it_cannot_draw(table, tmp_path: Path) -> None:
    from lfd_torch.viz import save_figure, violin

    with pytest.raises(UnknownNameError, match="order.*zzz.*valid names: a, b"):
        violin(table, "E1", order=["zzz"])
    with pytest.raises(PlotError, match="order"):
        violin(table, "E1", order="ab")
    with pytest.raises(PlotError, match="'E1' is not numeric"):
        violin(table.assign(E1="x"), "E1")
    with pytest.raises(PlotError, match="'E1' is not numeric"):
        violin(table.assign(E1=table.E1.astype(object)), "E1")
    with pytest.raises(PlotError, match="'E1' appears 2 times"):
        violin(pd.concat([table, table[["E1"]]], axis=1), "E1")
    fig = violin(table, "E1", order=["b", "a", "c"])  # a level without data still leaves an empty slot
    assert [t.get_text() for t in fig.axes[0].get_xticklabels()] == ["b", "a", "c"]
    for dpi in (0, -1, NAN, 1e6, "200"):
        with pytest.raises(PlotError, match="dpi"):
            save_figure(fig, tmp_path / "f.png", dpi=dpi)
    assert not list(tmp_path.iterdir())


# ============================================================================================ 10. collect
def _row(**kw) -> dict:
    row = {"experiment": "e", "shape": "s", "method": "m", "fold": 0, "seed": 0, "trajectory": 0,
           "config_hash": "h", "package_version": "v", "git_sha": "g", "E1": 1.0}  # fmt: skip
    return {**row, **kw}


@pytest.fixture()
def sweep(tmp_path: Path) -> Path:
    from lfd_torch.store import write_table

    write_table([_row()], tmp_path / "sweep" / "0" / "results.parquet")
    return tmp_path / "sweep"


def test_collect_cli_usage_errors_exit_2(sweep: Path, capsys) -> None:
    from lfd_torch.store.sweep import main

    for pattern in ("", "/abs/*.parquet"):
        with pytest.raises(SystemExit) as exc:
            main([str(sweep), "--pattern", pattern])
        assert exc.value.code == 2
        assert "--pattern" in capsys.readouterr().err


def test_collect_validates_every_output_before_writing_any(sweep: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    from lfd_torch.store import collect
    from lfd_torch.store.sweep import main

    first = tmp_path / "first.csv"
    first.write_text("old\n")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(StoreError, match="afile"):
        collect(sweep, save_to=[first, tmp_path / "afile" / "second.parquet"])
    assert first.read_text() == "old\n"
    with pytest.raises(StoreError, match="save_to"):
        collect(sweep, save_to=3)
    with pytest.raises(StoreError, match="pattern"):
        collect(sweep, "")
    # a write failure of a later output (disk full, no permission) leaves the earlier ones as they were
    real = pd.DataFrame.to_csv

    def fail_on_second(self, path, *a, **kw):
        if ".second.csv." in str(path):
            raise PermissionError(13, "Permission denied")
        return real(self, path, *a, **kw)

    monkeypatch.setattr(pd.DataFrame, "to_csv", fail_on_second)
    assert main([str(sweep), "--force", "--out", str(first), "--out", str(tmp_path / "second.csv")]) == 2
    assert "second.csv" in capsys.readouterr().err
    assert first.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "first.csv", "sweep"]
    monkeypatch.undo()
    assert len(collect(sweep, save_to=[first, tmp_path / "second.parquet"])) == 1  # valid input unchanged
    assert pd.read_csv(first)["E1"].tolist() == [1.0]


# ============================================================================================ 11. store arguments
def test_store_functions_check_their_arguments(sweep: Path, tmp_path: Path) -> None:
    from lfd_torch.store import atomic_write, finished_part, read_manifest, validate_table, write_table

    part = sweep / "0" / "results.parquet"
    with pytest.raises(StoreError, match="path"):
        read_manifest(None)
    with pytest.raises(StoreError, match="DataFrame"):
        validate_table([1])
    with pytest.raises(StoreError, match="manifest"):
        finished_part(part, None)
    with pytest.raises(StoreError, match="path"):
        atomic_write(None, lambda p: p.write_text("x"))
    with pytest.raises(InvalidArgumentError, match="writer"):
        atomic_write(tmp_path / "a.txt", None)
    with pytest.raises(StoreError, match=r"\.parquet"):
        write_table([_row()], tmp_path / "t.csv")
    assert not (tmp_path / "t.csv").exists() and not (tmp_path / "a.txt").exists()


def test_atomic_save_turns_io_failures_into_store_errors_and_keeps_the_old_file(tmp_path):
    """The package's own files (primitives, segmentations, libraries, stored figure data) are written through
    atomic_save: an unwritable folder (torch.save says RuntimeError) is a StoreError naming the file."""
    from lfd_torch.store import atomic_save

    target = tmp_path / "f.bin"
    target.write_bytes(b"old")

    def fails(exc):
        def writer(tmp):
            tmp.write_bytes(b"half")
            raise exc
        return writer

    for exc in (OSError("disk full"), RuntimeError("open file failed")):
        with pytest.raises(StoreError, match="f.bin"):
            atomic_save(target, fails(exc), what="test file")
        assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["f.bin"]
    with pytest.raises(ValueError, match="not an I/O"):  # the writer's own mistakes are not the store's
        atomic_save(target, fails(ValueError("not an I/O failure")))
    assert atomic_save(target, lambda tmp: tmp.write_bytes(b"new")) == target and target.read_bytes() == b"new"
