"""experiments/segmentation_variants.py: the comparison of stored segmentation tables against issue 7's checks."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

from bench_segmentation import segment_settings  # noqa: E402
from segmentation_variants import (  # noqa: E402
    DIRECTION_DEFAULTS, TABLES, VARIANTS, TableMismatch, Variant, markdown, summarize,
)

from lfd_torch.segmentation.synthetic import FAMILIES  # noqa: E402


def _synthetic_table(options, misses=(), families=FAMILIES):
    """A 10-seed x {1, 4}-demo table of ``families`` in which the cases in ``misses`` (family, n_demos, seed) miss."""
    rows = [{"method": "segment", "family": f, "n_demos": n, "seed": s, "all_switches": (f, n, s) not in misses,
             "exact_steps": True, "true_steps": 3, "found_steps": [3] * n, "median_error_pct": 0.1, "seconds": 1.0,
             "error": None}
            for f in families for n in (1, 4) for s in range(10)]  # fmt: skip
    return {"synthetic": rows, "provenance": {"git_sha": "abcdef0123", "segment_options": options},
            "synthetic_settings": {"noise_correlation": None, "n_steps": None, "rate": None}}


def _lasa_table(options, stable=(10, 9), groupings=(1, 2), seconds=((4.0, 6.0), (3.0, 11.0))):
    shapes = {}
    for i, (k, g, secs) in enumerate(zip(stable, groupings, seconds)):
        shapes[f"shape{i}"] = {"modal_steps_per_demo": [[3, 10], [2, k]], "distinct_route_groupings": g,
                               "runs": [{"seed": j, "seconds": s} for j, s in enumerate(secs)]}
    return {"settings": {"seeds": 10, "selection": "map", "options": options}, "shapes": shapes}


def _write(tmp_path, name, table):
    (tmp_path / name).write_text(json.dumps(table))
    return name


def test_a_family_row_below_the_bar_is_reported_with_its_count(tmp_path):
    misses = {("straight_const_3d", 1, 0), ("straight_const_3d", 1, 5), ("scoop_const_3d", 4, 2)}
    name = _write(tmp_path, "syn.json", _synthetic_table({"direction_noise": 0.05}, misses))
    lasa = _write(tmp_path, "lasa.json", _lasa_table({"direction_noise": 0.05}))
    s = summarize(Variant("tight", {"direction_noise": 0.05}, name, None, lasa), tmp_path)
    assert s["every"] == pytest.approx(277 / 280)
    assert s["every_1"] == pytest.approx(138 / 140) and s["every_4"] == pytest.approx(139 / 140)
    assert s["below"] == [("straight_const_3d", 1, 8)]  # one miss in a row of 10 is still 9 of 10
    assert s["lasa"] == {"stable": 9, "groupings": 2, "median_s": 5.0, "max_s": 11.0}
    assert s["commit"] == "abcdef0"
    text = markdown([s])
    assert "straight_const_3d (1 demo) 8" in text and "| 9 of 10, 2 | 5.0 / 11.0 |" in text


def test_a_table_of_other_options_or_other_cases_is_refused(tmp_path):
    name = _write(tmp_path, "syn.json", _synthetic_table({"direction_noise": 0.1}))
    with pytest.raises(TableMismatch, match="syn.json"):
        summarize(Variant("tight", {"direction_noise": 0.05}, name), tmp_path)
    short = _synthetic_table({}, families=list(FAMILIES)[:-1])
    with pytest.raises(TableMismatch, match="not the 280"):
        summarize(Variant("defaults", {}, _write(tmp_path, "short.json", short)), tmp_path)
    other = _synthetic_table({})
    other["synthetic_settings"]["rate"] = 10.0
    with pytest.raises(TableMismatch, match="rate"):
        summarize(Variant("defaults", {}, _write(tmp_path, "rate.json", other)), tmp_path)
    with pytest.raises(TableMismatch, match="not found"):
        summarize(Variant("defaults", {}, "missing.json"), tmp_path)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(TableMismatch, match="not valid JSON"):
        summarize(Variant("defaults", {}, "bad.json"), tmp_path)


def test_tables_with_resolved_settings_are_checked_against_todays_signature(tmp_path):
    """A table that records segment()'s resolved keywords is read for a variant whose options give exactly those
    today; a table of the direction defaults (options only) is read for such a variant with the direction emission
    pinned in its column, and refused for a variant of today's defaults."""
    table = _synthetic_table({"slope_scale": 3.0})
    table["provenance"]["segment_settings"] = segment_settings({"slope_scale": 3.0})
    name = _write(tmp_path, "new.json", table)
    s = summarize(Variant("vaguer", {"slope_scale": 3.0}, name, direction_defaults=False), tmp_path)
    assert s["options"] == {"slope_scale": 3.0} and s["every"] == 1.0
    with pytest.raises(TableMismatch, match="block_emission"):  # same recorded options, other resolved settings
        summarize(Variant("vaguer", {"slope_scale": 3.0}, name, direction_defaults=True), tmp_path)
    with pytest.raises(TableMismatch, match="slope_scale"):
        summarize(Variant("vaguer", {"slope_scale": 2.0}, name, direction_defaults=False), tmp_path)
    old = _write(tmp_path, "old.json", _synthetic_table({"slope_scale": 3.0}))
    s = summarize(Variant("vaguer", {"slope_scale": 3.0}, old), tmp_path)
    assert s["options"] == {"slope_scale": 3.0, **DIRECTION_DEFAULTS}
    s = summarize(Variant("block", {"block_emission": True}, _write(tmp_path, "b.json", _synthetic_table(
        {"block_emission": True}))), tmp_path)
    assert s["options"] == {"block_emission": True, "position_mixture": False}
    with pytest.raises(TableMismatch, match="records no segment settings"):
        summarize(Variant("vaguer", {"slope_scale": 3.0}, old, direction_defaults=False), tmp_path)


def test_every_registered_variant_reads_its_stored_tables():
    """The registry names tables that exist and hold the options it says; the defaults' rows below the bar, counted
    here case by case from the stored rows, are the ones reported."""
    summaries = [summarize(v) for v in VARIANTS]
    assert [s["label"] for s in summaries] == [v.label for v in VARIANTS]
    rows = json.loads((TABLES / VARIANTS[0].synthetic).read_text())["synthetic"]
    hits = {}
    for r in rows:
        hits[(r["family"], r["n_demos"])] = hits.get((r["family"], r["n_demos"]), 0) + bool(r["all_switches"])
    assert summaries[0]["below"] == [(f, n, k) for (f, n), k in hits.items() if k < 9]
    assert summaries[0]["every"] == pytest.approx(sum(bool(r["all_switches"]) for r in rows) / len(rows))


def test_the_readme_table_is_the_one_the_command_writes():
    """The README's side-by-side table is the command's output for the stored tables, not a hand-made copy."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    table = markdown([summarize(v) for v in VARIANTS]).split("\n\nRows below")[0]
    assert table in readme
