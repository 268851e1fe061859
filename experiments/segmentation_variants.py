"""The segmentation's measured settings side by side, against issue 7's acceptance checks (stored tables only).

    python experiments/segmentation_variants.py [--tables results/tables] \
        [--markdown results/tables/segmentation_variants.md]

Every setting of :func:`lfd_torch.segmentation.segment` measured on the development benchmark (the 280 synthetic
cases of ``bench_segmentation.py --parts synthetic``: 14 families x {1, 4} demonstrations x 10 data seeds), and
where it was also measured, on the held-out families (``--families rounded_const_2d rounded_const_3d rounded_vary_2d
rounded_vary_3d``, 80 cases) and on LASA Multi_Models_1-4 over 10 sampler seeds (``bench_segmentation_seeds.py``).
Nothing is rerun: each row reads the tables named in :data:`VARIANTS`, checks that each table's recorded options are
the row's (a mismatch is an error, not a silent relabel), and reports

    every switch   share of cases with every switch within 3 % (all / 1 demo / 4 demos), 280 cases
    rows < 9       family x demo-count rows (of 28) with every switch on fewer than 9 of 10 cases, issue 7's
                   ">= 90 % in every family, with 1 and with 4 demonstrations"; the rows are listed below the table
    held out       every switch on the 80 held-out cases
    LASA seeds     the fewest seeds (of 10) on which a demonstration gets its most common step count, over the 28
                   demonstrations of Multi_Models_1-4 (issue 7 asks >= 9), and the most route groupings of a shape
    LASA s         median / slowest wall time of one segmentation (issue 7 asks <= 10 s), as stored: the tables were
                   made on one machine but not all with the other core idle
    commit         the code that made the synthetic table (each table records its own ``git_sha``)

A dash is a benchmark that was not run for that setting.

Options are relative to :func:`segment`'s defaults, which have changed: tables made before the switch to the block
emission with positions as a mixture (``Variant.direction_defaults``) hold options relative to the direction
emission, and the column shows what to pass today for the same setting (those options plus
:data:`DIRECTION_DEFAULTS` where the row does not set them). Tables made since record every keyword as the call
resolved it (``segment_settings``), which is checked against this checkout's signature with the row's options.
"""

from __future__ import annotations

import argparse
import json
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from lfd_torch.segmentation.synthetic import FAMILIES, HELD_OUT_FAMILIES
from bench_segmentation import segment_settings, summarize_synthetic

ROOT = Path(__file__).resolve().parents[1]
TABLES = ROOT / "results" / "tables"

#: The acceptance bar of issue 7: every switch on at least this many of the 10 cases of a family row.
ROW_BAR = 9


#: segment()'s emission defaults before the block emission with positions as a mixture became the default: what a
#: table made then (without ``segment_settings``) ran where its options do not say otherwise.
DIRECTION_DEFAULTS: dict[str, Any] = {"block_emission": False, "position_mixture": False}


@dataclass(frozen=True)
class Variant:
    """One setting of ``segment``: its options as its tables record them, the tables that measured it (file names
    under the tables dir) and whether they were made under the direction emission's defaults."""

    label: str
    options: dict[str, Any] = field(default_factory=dict)
    synthetic: str | None = None
    held_out: str | None = None
    lasa: str | None = None
    direction_defaults: bool = True

    def current_options(self) -> dict[str, Any]:
        """The options that give this setting with today's defaults."""
        if not self.direction_defaults:
            return dict(self.options)
        return {**self.options, **{k: v for k, v in DIRECTION_DEFAULTS.items() if k not in self.options}}


#: The measured settings, defaults first. Options as passed to ``--segment-option`` (and recorded in each table).
VARIANTS: tuple[Variant, ...] = (
    Variant("defaults", {}, "bench_segmentation_segment.json", "bench_segmentation_held_out.json",
            "bench_segmentation_seeds_default.json", direction_defaults=False),
    Variant("direction emission (the earlier defaults)", {}, "bench_segmentation_segment_directions.json",
            "bench_segmentation_held_out_directions.json", "bench_segmentation_seeds_directions.json"),
    Variant("straight fields favoured", {"straight_weight": 0.99}, "bench_segmentation_segment_straight99.json"),
    Variant("vaguer slope prior", {"slope_scale": 3.0}, "bench_segmentation_segment_slope3.json",
            "bench_segmentation_held_out_slope3.json", "bench_segmentation_seeds_slope3.json"),
    Variant("two slope scales", {"slope_scale_mix": 3.0}, "bench_segmentation_segment_slope_mix3.json",
            "bench_segmentation_held_out_slope_mix3.json", "bench_segmentation_seeds_slope_mix3.json"),
    Variant("rotation fields", {"rotation_weight": 0.5}, "bench_segmentation_segment_rotation05.json",
            "bench_segmentation_held_out_rotation05.json", "bench_segmentation_seeds_rotation05.json"),
    Variant("block emission", {"block_emission": True, "position_weight": 0.0}, "bench_segmentation_segment_block.json",
            "bench_segmentation_held_out_block.json", "bench_segmentation_seeds_block.json"),
    Variant("block emission, block-scored search", {"block_emission": True, "position_weight": 0.0},
            "bench_segmentation_segment_block_search.json", "bench_segmentation_held_out_block_search.json",
            "bench_segmentation_seeds_block_search.json"),
    Variant("block emission with the position term", {"block_emission": True, "position_weight": None},
            "bench_segmentation_segment_block_position.json"),
    Variant("block emission, positions as a mixture",
            {"block_emission": True, "position_weight": None, "position_mixture": True},
            "bench_segmentation_segment_block_position_mixture.json",
            "bench_segmentation_held_out_block_position_mixture.json",
            "bench_segmentation_seeds_block_position_mixture.json"),
    Variant("tight tolerance", {"direction_noise": 0.05}, "bench_segmentation_segment_tolerance005.json", None,
            "bench_segmentation_seeds_tolerance005.json"),
    Variant("learned correlated tolerance", {"tolerance_correlation": None},
            "bench_segmentation_segment_learned_tolerance_kalman.json",
            "bench_segmentation_held_out_learned_tolerance.json",
            "bench_segmentation_seeds_learned_tolerance_kalman.json"),
    Variant("learned correlated tolerance, polished split", {"tolerance_correlation": None},
            "bench_segmentation_segment_learned_tolerance_polish.json",
            "bench_segmentation_held_out_learned_tolerance_polish.json",
            "bench_segmentation_seeds_learned_tolerance_polish.json"),
    Variant("learned tolerance, weak position term", {"tolerance_correlation": None, "position_weight": 0.1},
            "bench_segmentation_segment_learned_tolerance_kalman_position01.json"),
    Variant("learned tolerance, demonstration offsets", {"tolerance_correlation": None, "demo_offset": 16},
            "bench_segmentation_segment_learned_tolerance_demo_offset16.json"),
    Variant("weak position term", {"position_weight": 0.1}, "bench_segmentation_segment_position01.json"),
    Variant("strong position term", {"position_weight": 0.6}, "bench_segmentation_segment_position06.json"),
    Variant("positions as a mixture", {"position_mixture": True}, "bench_segmentation_segment_position_mixture.json"),
    Variant("pace level per run", {"dwell_pace": True}, "bench_segmentation_segment_dwell_pace.json",
            "bench_segmentation_held_out_dwell_pace.json", "bench_segmentation_seeds_dwell_pace.json"),
    Variant("demonstration offsets", {"demo_offset": 1}, "bench_segmentation_segment_demo_offset1.json"),
    Variant("tight tolerance, demonstration offsets", {"demo_offset": 16, "direction_noise": 0.05},
            "bench_segmentation_segment_tolerance005_demo_offset16.json",
            "bench_segmentation_held_out_tolerance005_demo_offset16.json",
            "bench_segmentation_seeds_tolerance005_demo_offset16.json"),
    Variant("tight AR(0.9) tolerance, demonstration offsets",
            {"demo_offset": 16, "direction_noise": 0.05, "tolerance_correlation": 0.9},
            "bench_segmentation_segment_tolerance005_ar09_demo_offset16.json", None,
            "bench_segmentation_seeds_tolerance005_ar09_demo_offset16.json"),
)


class TableMismatch(ValueError):
    """A stored table does not hold what its variant says (other options, other cases)."""


def _load(tables: Path, name: str) -> dict[str, Any]:
    path = tables / name
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise TableMismatch(f"table {name!r} not found under {tables}") from exc
    except json.JSONDecodeError as exc:
        raise TableMismatch(f"table {name!r} is not valid JSON: {exc}") from exc


def _same_options(stored: dict[str, Any], settings: dict[str, Any] | None, variant: Variant, name: str,
                  **extra: Any) -> None:
    """The table's recorded options are the variant's: its resolved ``settings`` when it has them (against this
    checkout's signature with the variant's current options and ``extra``), else its options as recorded, for a
    table of the direction defaults."""
    if settings is not None:
        wanted = json.loads(json.dumps(segment_settings({**variant.current_options(), **extra})))
        if settings != wanted:
            diff = {k: (settings.get(k), wanted.get(k)) for k in set(settings) | set(wanted)
                    if settings.get(k) != wanted.get(k)}
            raise TableMismatch(f"table {name!r} was made with other settings than its variant's (table, variant): "
                                f"{diff}")
        return
    if not variant.direction_defaults:
        raise TableMismatch(f"table {name!r} records no segment settings, and its variant is not of the direction "
                            "defaults")
    if stored != variant.options:
        raise TableMismatch(f"table {name!r} was made with options {stored}, its variant says {variant.options}")


def _segment_rows(table: dict[str, Any], name: str, families: dict[str, Any], variant: Variant) -> list[dict]:
    """The ``segment`` rows of a synthetic table, checked to be 10 data seeds x {1, 4} demos of exactly ``families``
    under the default benchmark settings and the variant's options."""
    provenance = table.get("provenance", {})
    _same_options(provenance.get("segment_options", {}), provenance.get("segment_settings"), variant, name)
    settings = table.get("synthetic_settings", {})
    for key in ("noise_correlation", "n_steps", "rate", "noise_scale"):
        if settings.get(key) is not None:
            raise TableMismatch(f"table {name!r} is not the default benchmark: {key}={settings[key]}")
    rows = [r for r in table.get("synthetic", []) if r["method"] == "segment"]
    cells = {(r["family"], r["n_demos"], r["seed"]) for r in rows}
    expected = {(f, n, s) for f in families for n in (1, 4) for s in range(10)}
    if cells != expected or len(rows) != len(expected):
        raise TableMismatch(f"table {name!r} holds {len(rows)} segment cases, not the {len(expected)} of "
                            f"{len(families)} families x {{1, 4}} demos x 10 seeds")
    return rows


def _shares(rows: list[dict]) -> dict[Any, float]:
    """Every-switch share of the cases per demonstration count (1, 4) and over all ("all"), from the benchmark's
    own summary."""
    return {r["n_demos"]: r["all_switches"] for r in summarize_synthetic(rows)["totals"]}


def rows_below_bar(rows: list[dict], bar: int = ROW_BAR) -> list[tuple[str, int, int]]:
    """(family, n_demos, cases with every switch) of the family rows (10 cases each) below ``bar`` of their cases, in
    table order, from the benchmark's own per-family summary."""
    found = [(r["family"], r["n_demos"], round(r["all_switches"] * r["cases"]))
             for r in summarize_synthetic(rows)["per_family"]]
    return [(f, n, k) for f, n, k in found if k < bar]


def lasa_summary(table: dict[str, Any], name: str, variant: Variant) -> dict[str, Any]:
    """Fewest seeds with the modal count over all demonstrations, most route groupings, median / max seconds."""
    settings = table.get("settings", {})
    _same_options(settings.get("options", {}), settings.get("segment_settings"), variant, name, selection="map")
    if settings.get("selection", "map") != "map" or "cases" in settings:
        raise TableMismatch(f"table {name!r} is not a LASA run of the default selection")
    shapes = table["shapes"]
    stable = min(seeds for s in shapes.values() for _, seeds in s["modal_steps_per_demo"])
    groupings = max(s["distinct_route_groupings"] for s in shapes.values())
    seconds = [run["seconds"] for s in shapes.values() for run in s["runs"]]
    return {"stable": stable, "groupings": groupings, "median_s": statistics.median(seconds), "max_s": max(seconds)}


def summarize(variant: Variant, tables: Path = TABLES) -> dict[str, Any]:
    """One row of the comparison (see the module docstring); None where a benchmark was not run."""
    out: dict[str, Any] = {"label": variant.label, "options": variant.current_options()}
    if variant.synthetic:
        table = _load(tables, variant.synthetic)
        rows = _segment_rows(table, variant.synthetic, FAMILIES, variant)
        shares = _shares(rows)
        out.update(every=shares["all"], every_1=shares[1], every_4=shares[4], below=rows_below_bar(rows),
                   commit=str(table["provenance"].get("git_sha", "?"))[:7])
    if variant.held_out:
        rows = _segment_rows(_load(tables, variant.held_out), variant.held_out, HELD_OUT_FAMILIES, variant)
        out["held_out"] = _shares(rows)["all"]
    if variant.lasa:
        out["lasa"] = lasa_summary(_load(tables, variant.lasa), variant.lasa, variant)
    return out


def _options_text(options: dict[str, Any]) -> str:
    return " ".join(f"{k}={v}" for k, v in options.items()) or "(none)"


def markdown(summaries: list[dict[str, Any]]) -> str:
    pct = "{:.1%}".format
    lines = [
        "| setting | `--segment-option` | every switch, 280 cases (1 / 4 demos) | rows < 9 of 10 (of 28) | held out, "
        "80 cases | LASA: fewest seeds with the modal count, route groupings | LASA s, median / slowest | commit |",
        "|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    for s in summaries:
        every = f"{pct(s['every'])} ({pct(s['every_1'])} / {pct(s['every_4'])})" if "every" in s else "-"
        below = str(len(s["below"])) if "below" in s else "-"
        held = pct(s["held_out"]) if "held_out" in s else "-"
        lasa = s.get("lasa")
        stab = f"{lasa['stable']} of 10, {lasa['groupings']}" if lasa else "-"
        secs = f"{lasa['median_s']:.1f} / {lasa['max_s']:.1f}" if lasa else "-"
        lines.append(f"| {s['label']} | `{_options_text(s['options'])}` | {every} | {below} | {held} | {stab} | "
                     f"{secs} | {s.get('commit', '-')} |")
        if s.get("below"):
            rows = ", ".join(f"{f} ({n} demo{'s' if n > 1 else ''}) {k}" for f, n, k in s["below"])
            notes.append(f"- {s['label']}: {rows}")
    return "\n".join(lines) + "\n\nRows below 9 of 10 (family, demonstrations, cases with every switch):\n\n" + \
        "\n".join(notes) + "\n"


def main(argv: list[str] | None = None) -> None:
    torch.set_num_threads(1)  # only JSON is read here, but the package import brings torch's thread pool
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tables", type=Path, default=TABLES, help="directory of the stored benchmark tables")
    ap.add_argument("--markdown", type=Path, default=None, help="also write the table to this file")
    args = ap.parse_args(argv)
    text = markdown([summarize(v, args.tables) for v in VARIANTS])
    print(text, end="")
    if args.markdown is not None:
        tmp = args.markdown.with_name(args.markdown.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(args.markdown)


if __name__ == "__main__":
    main()
