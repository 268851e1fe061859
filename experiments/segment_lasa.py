"""BP-GM-HMM segmentation of LASA Multi_Models_1..4 and of a 3-D multi-step set (paper Sec. III-A, Fig. 2).

No number of steps is given. Demonstrations that start in different places follow different routes (LASA
Multi_Models mixes 2-3 routes), so each data set is first split into routes by its start points
(``group_by_start``) and every route is segmented on its own. For every route the table lists, per step m: the
attractor g_m (mean end point of step m; the last one is the data set's attractor), the HMM states of its subtask
space A_m, the mean start/end sample and the mean fraction of the demonstration it covers, the number of steps, the
sampler time, the step counts each demonstration had before the consensus, the demonstrations that were forced to
the consensus count (``demo:own_count``) and those that had to be cut evenly.
Figures show each demonstration coloured by step over the regions where p(x | A_m) is the largest step density.

    python experiments/segment_lasa.py
    python experiments/segment_lasa.py seed=1 segmentation.n_iterations=80
    python experiments/segment_lasa.py -m seed=0,1,2
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import hydra
import pandas as pd
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from lfd_torch.data import Demos, load_lasa
from lfd_torch.segmentation.plot import plot_segmentation
from lfd_torch.segmentation.synthetic import multi_step_demos
from lfd_torch.store import atomic_write, run_manifest, write_table
from lfd_torch.utils import derive_seed

log = logging.getLogger(__name__)


def route_groups(demos: Demos, fraction: float | None) -> list[list[int]]:
    """Demonstrations that start together: single-linkage groups of start points closer than ``fraction`` times
    the largest extent of the data (all in one group when ``fraction`` is None).

    LASA Multi_Models sets mix routes from different starts (e.g. Multi_Models_3: 4 from the left, 3 from the top
    right) that share no step sequence, so the ordered steps of Table I are found per route.
    """
    n = demos.n_demos
    if fraction is None:
        return [list(range(n))]
    x = demos.samples()[0]
    threshold = float(fraction) * float((x.max(0).values - x.min(0).values).max())
    close = torch.cdist(demos.start_points, demos.start_points) <= threshold
    group = list(range(n))
    changed = True
    while changed:  # connected components by label propagation
        changed = False
        for i in range(n):
            for j in range(n):
                if close[i, j] and group[j] < group[i]:
                    group[i] = group[j]
                    changed = True
    labels = sorted(set(group))
    return [[i for i in range(n) if group[i] == g] for g in labels]


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


def run(cfg: DictConfig) -> dict[str, Any]:
    """Segment every data set; returns the table and the paths written."""
    out_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(cfg.get("out_dir", "."))
    manifest = run_manifest(cfg, seed=cfg.seed)
    segmenter = instantiate(cfg.segmentation)
    method = (HydraConfig.get().runtime.choices.get("segmentation") if HydraConfig.initialized() else None) or "bp_gm_hmm"
    rows: list[dict[str, Any]] = []
    written: list[Path] = []
    segmentations = {}
    for shape, all_demos in datasets(cfg).items():
        groups = route_groups(all_demos, cfg.get("group_by_start"))
        for r, members in enumerate(groups):
            name = shape if len(groups) == 1 else f"{shape}_route{r + 1}"
            demos = all_demos[members]
            g = torch.Generator().manual_seed(derive_seed(cfg.experiment, name, cfg.seed))
            t0 = time.perf_counter()
            seg = segmenter(demos, generator=g)
            seconds = time.perf_counter() - t0
            segmentations[name] = seg
            log.info("%s (demos %s): %d steps in %.1f s", name, members, seg.n_steps, seconds)
            counts = seg.info.get("step_counts_before_consensus", {})
            for step_row in seg.table():
                row = {
                    "experiment": cfg.experiment, "shape": name, "method": method, "fold": 0, "seed": int(cfg.seed),
                    "trajectory": int(step_row["step"]), "demos": " ".join(map(str, members)), "n_steps": seg.n_steps,
                    "dim": demos.dim, "seconds": seconds,
                    "counts_before_consensus": " ".join(f"{k}:{v}" for k, v in sorted(counts.items())),
                    "forced_to_consensus": " ".join(
                        f"{members[i]}:{c}" for i, c in sorted(seg.info.get("forced_to_consensus", {}).items())
                    ),
                    "equal_cut_fallback": " ".join(str(members[i]) for i in seg.info.get("equal_cut_fallback", [])),
                }  # fmt: skip
                row.update(step_row)
                rows.append(row)
            if cfg.figures:
                fig_dir = Path(cfg.paths.figures) if cfg.publish else out_dir
                path = fig_dir / f"{cfg.experiment}_{name}.png"
                plot_segmentation(seg, demos, path, title=f"{name}: {seg.n_steps} steps")
                written.append(path)
    table = pd.DataFrame(rows)
    written.append(write_table(table, out_dir / "results.parquet", manifest=manifest))
    if cfg.publish:
        tables = Path(cfg.paths.tables)
        written.append(write_table(table, tables / f"{cfg.experiment}.parquet", manifest=manifest))
        md = table.drop(columns=["experiment", "method", "fold"]).to_markdown(index=False, floatfmt=".4g")
        written.append(atomic_write(tables / f"{cfg.experiment}.md", lambda p: p.write_text(md + "\n")))
    return {"table": table, "segmentations": segmentations, "written": written}


@hydra.main(config_path="../conf", config_name="segment_lasa", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = run(cfg)
    print(result["table"].to_string(index=False))


if __name__ == "__main__":
    main()
