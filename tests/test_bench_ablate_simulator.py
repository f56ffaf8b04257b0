"""bench.ablate_simulator: every mechanism it turns off is a setting the draft takes, and
each one changes the draft."""
from __future__ import annotations

import pytest

from bench.ablate_simulator import MECHANISMS, markdown, summary
from core.engine.presets import preset


@pytest.mark.parametrize("name", [n for n in MECHANISMS if n != "shipped"])
def test_each_ablation_is_a_valid_change_of_the_draft(name):
    draft = preset("draft")
    changed = draft.with_overrides(MECHANISMS[name])
    assert changed != draft
    for key, value in MECHANISMS[name].items():
        section, _, leaf = key.partition(".")
        assert getattr(getattr(changed, section), leaf) in (value, tuple(value) if isinstance(value, list) else value)


def test_the_table_reads_the_probe_report():
    def suite(switches):
        scores = {m: {"diffuse": {"angular_deg": a}} for m, a in (("constant", 4.0), ("field", 2.0))}
        return {"scores": scores, "cpu_s": {"field": 12.0},
                "ratios": {"field": {"vs_constant": {"diffuse.si_rmse": 0.7, "matte.si_rmse": 0.9},
                                     "vs_prior": {"diffuse.si_rmse": 1.01, "matte.si_rmse": 1.04}}},
                "interval_90": {"field": {"vs_constant": {"diffuse.si_rmse": [0.6, 0.8]}}},
                "series": {"field": {"switches": switches}},
                "per_probe": [{"peak_luminance": {"truth": 100.0, "field": f}, "peak_direction_deg": {"field": a}}
                              for f, a in ((1.0, 40.0), (100.0, 3.0))]}

    rows = summary({"suites": {"spatial": suite([]), "temporal": suite([{"abs_diff": 0.03}, {"abs_diff": 0.15}])}})
    assert rows["spatial"]["diffuse_angle"] == 0.5 and rows["spatial"]["switch_error"] is None
    assert rows["temporal"]["switch_error"] == 0.15 and rows["temporal"]["worst_vs_prior"] == 1.04
    assert rows["temporal"]["peak_vs_truth"] == 0.1 and rows["temporal"]["peak_found"] == "1/2"
    table = markdown({"shipped": rows})
    assert "| shipped | temporal | 0.700 [0.60, 0.80] | 0.900 | 0.500 | 1.040 | 0.150 | 0.100 | 1/2 | 12.0 |" in table


def test_a_report_from_before_the_peak_direction_leaves_its_cell_empty():
    report = {"suites": {"spatial": {
        "scores": {m: {"diffuse": {"angular_deg": 1.0}} for m in ("constant", "field")}, "cpu_s": {"field": 1.0},
        "ratios": {"field": {"vs_constant": {"diffuse.si_rmse": 1.0, "matte.si_rmse": 1.0}, "vs_prior": {"x": 1.0}}},
        "interval_90": {"field": {"vs_constant": {"diffuse.si_rmse": [0.9, 1.1]}}},
        "per_probe": [{"peak_luminance": {"truth": 1.0, "field": 1.0}}]}}}
    rows = summary(report)
    assert rows["spatial"]["peak_found"] is None
    assert "| 1.000 |  | 1.0 |" in markdown({"shipped": rows})
