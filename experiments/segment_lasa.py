"""BP-GM-HMM segmentation of LASA Multi_Models_1..4 and of a 3-D multi-step set (paper Sec. III-A, Fig. 2).

No number of steps is given, and all demonstrations of a data set are segmented together: LASA Multi_Models mixes
2-3 routes, which the model separates by its features (``Segmentation.routes``). The table lists, per step m: its
route, the HMM state, the attractor g_m (mean end point of step m; the last step of a route ends at the data set's
attractor), the number of pieces and their mean start/end fraction, the number of steps of the data set and of each
demonstration, and the sampler time.
Figures show each demonstration coloured by step over the regions where p(x | A_m) is the largest step density.

    python experiments/segment_lasa.py
    python experiments/segment_lasa.py seed=1 segmentation.n_iterations=80
    python experiments/segment_lasa.py -m seed=0,1,2
    python experiments/segment_lasa.py +experiment=segment_lasa_publish    # the README's table and figures
    python experiments/segment_lasa.py +experiment=segment_lasa_map_publish    # selection="map", position_weight=None

``publish=true`` writes into ``paths.tables`` / ``paths.figures`` and stores each data set's segmentation and
demonstrations under ``paths.libraries``/<experiment>/<name>/ (what ``experiments/figures.py`` redraws the figures
from); it is refused in a multirun (every job would overwrite the published files).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import hydra
import pandas as pd
import torch
from tqdm import tqdm

torch.set_num_threads(1)  # the busy-waiting default pool is ~10x slower on a loaded 2-core box
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from lfd_torch.data import Demos, load_lasa
from lfd_torch.segmentation.plot import plot_segmentation
from lfd_torch.segmentation.synthetic import multi_step_demos
from lfd_torch.store import atomic_write, prepare_job, staged_results, write_table
from lfd_torch.store.job import RESULTS_NAME
from lfd_torch.utils import derive_seed
from lfd_torch.viz.stored import save_demos

#: Unit of each data set's state, on the figure axes (LASA: mm; the synthetic set has arbitrary units).
UNITS = {"synthetic_3d": "a.u."}

log = logging.getLogger(__name__)


def datasets(cfg: DictConfig) -> dict[str, Demos]:
    """The LASA shapes of ``cfg.shapes`` and, unless null, the synthetic 3-D set."""
    out = {name: load_lasa(name) for name in cfg.shapes}
    syn_cfg = cfg.get("synthetic_3d")
    if syn_cfg is not None:
        kw = OmegaConf.to_container(syn_cfg, resolve=True)
        assert isinstance(kw, dict)
        data_seed = int(kw.pop("data_seed", 0))
        syn = multi_step_demos(torch.Generator().manual_seed(data_seed), dim=3, **kw)
        out["synthetic_3d"] = syn.demos
    return out


def draw(name: str, segmentation: Any, demos: Demos, path: Path) -> Path:
    """The figure of one data set (shared with ``experiments/figures.py``)."""
    plot_segmentation(segmentation, demos, path, title=f"{name}: {segmentation.n_steps} steps, "
                      f"{segmentation.n_routes} routes", unit=UNITS.get(name, "mm"))  # fmt: skip
    return path


def store(name: str, segmentation: Any, demos: Demos, libraries: Path, experiment: str = "segment_lasa") -> list[Path]:
    """Store what :func:`draw` needs under ``libraries/<experiment>/<name>/``."""
    where = libraries / experiment / name
    return [segmentation.save(where / "segmentation.pt"), save_demos(demos, where / "demos.pt", velocities=False)]


def run(cfg: DictConfig) -> dict[str, Any]:
    """Segment every data set; returns the table and the paths written.

    Raises:
        InvalidArgumentError: ``seed`` not an integer, or ``publish=true`` in a Hydra multirun (every job would
            overwrite the published table and figures; run the published configuration alone,
            ``+experiment=segment_lasa_publish``).
    """
    job = prepare_job(cfg)
    out_dir, manifest = job.out_dir, job.manifest
    segmenter = instantiate(cfg.segmentation)
    method = (HydraConfig.get().runtime.choices.get("segmentation") if HydraConfig.initialized() else None) or "bp_gm_hmm"
    rows: list[dict[str, Any]] = []
    written: list[Path] = []
    segmentations = {}
    for name, demos in tqdm(list(datasets(cfg).items()), desc="segment_lasa", unit="set", disable=not cfg.get("progress", True)):
        g = torch.Generator().manual_seed(derive_seed(cfg.experiment, name, cfg.seed))
        t0 = time.perf_counter()
        seg = segmenter(demos, generator=g)
        seconds = time.perf_counter() - t0
        segmentations[name] = seg
        log.info("%s: %d steps, %d routes in %.1f s", name, seg.n_steps, seg.n_routes, seconds)
        for step_row in seg.table():
            route = int(step_row["route"])
            members = [i for i in range(demos.n_demos) if int(seg.route_of[i]) == route]
            row = {
                "experiment": cfg.experiment, "shape": name, "method": method, "fold": 0, "seed": int(cfg.seed),
                "trajectory": int(step_row["step"]), "demos": " ".join(map(str, members)), "n_steps": seg.n_steps,
                "steps_per_demo": " ".join(str(len(seg.step_sequence(i))) for i in members),
                "dim": demos.dim, "seconds": seconds,
            }  # fmt: skip
            row.update(step_row)
            rows.append(row)
        if cfg.figures:
            fig_dir = Path(cfg.paths.figures) if cfg.publish else out_dir
            path = fig_dir / f"{cfg.experiment}_{name}.png"
            written.append(draw(name, seg, demos, path))
        if cfg.publish:
            written += store(name, seg, demos, Path(cfg.paths.libraries), cfg.experiment)
    table = pd.DataFrame(rows)
    written.append(write_table(table, out_dir / RESULTS_NAME, manifest=manifest))
    if cfg.publish:
        tables = Path(cfg.paths.tables)
        written.append(write_table(table, tables / f"{cfg.experiment}.parquet", manifest=manifest))
        md = table.drop(columns=["experiment", "method", "fold"]).to_markdown(index=False, floatfmt=".4g")
        written.append(atomic_write(tables / f"{cfg.experiment}.md", lambda p: p.write_text(md + "\n")))
    return {"table": table, "segmentations": segmentations, "written": written}


@hydra.main(config_path="../conf", config_name="segment_lasa", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with staged_results(cfg):  # published outputs replace the old ones together, only when the run succeeds
        result = run(cfg)
    print(result["table"].to_string(index=False))


if __name__ == "__main__":
    main()
