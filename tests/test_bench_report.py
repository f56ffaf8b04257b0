"""Light tests of the bench's plumbing: Pareto front, log-log fit, step lag, scoring, report.

The bench itself (distillation runs) is not part of the test suite."""
from __future__ import annotations

import json
import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from bench.report import markdown, pareto_front, sanitize, time_to_answer
from bench.scaling import loglog_exponent
from bench.suite.evaluation import score_probe, step_response, switch_lag
from core.conventions import equirect_directions

finite_floats = st.floats(min_value=1e-3, max_value=1e3, allow_nan=False)


# ---------------------------------------------------------------------------------------
# Pareto front
# ---------------------------------------------------------------------------------------
def test_pareto_front_small_case():
    pts = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (4.0, 1.0), (0.5, 9.0)]
    # (3, 4) is dominated by (2, 3); all others trade time for error
    assert pareto_front(pts) == [4, 0, 1, 3]


@given(st.lists(st.tuples(finite_floats, finite_floats), min_size=1, max_size=30))
@settings(max_examples=60, deadline=None)
def test_pareto_front_is_exactly_the_non_dominated_set(pts):
    front = set(pareto_front(pts))

    def dominated(i):
        return any(pts[j][0] <= pts[i][0] and pts[j][1] <= pts[i][1] and pts[j] != pts[i] for j in range(len(pts)))

    for i in range(len(pts)):
        if dominated(i):
            assert i not in front
    # every non-dominated distinct point is represented (duplicates keep one copy)
    assert {pts[i] for i in range(len(pts)) if not dominated(i)} == {pts[i] for i in front}


# ---------------------------------------------------------------------------------------
# Scaling fit
# ---------------------------------------------------------------------------------------
@given(st.floats(min_value=-3, max_value=3), st.floats(min_value=1e-3, max_value=1e3))
@settings(max_examples=50, deadline=None)
def test_loglog_exponent_recovers_power_law(k, c):
    xs = [1.0, 2.0, 4.0, 16.0]
    assert loglog_exponent(xs, [c * x**k for x in xs]) == pytest.approx(k, abs=1e-9)


def test_loglog_exponent_ignores_missing_points_and_needs_two():
    assert loglog_exponent([1, 2, 4], [3.0, None, 12.0]) == pytest.approx(1.0)
    assert loglog_exponent([1, 2], [3.0, None]) is None


# ---------------------------------------------------------------------------------------
# Switch lag
# ---------------------------------------------------------------------------------------
def _step(times, at, hi=10.0, lo=1.0):
    return torch.where(times < at, torch.full_like(times, hi), torch.full_like(times, lo))


def test_switch_lag_of_delayed_step_is_the_delay():
    times = torch.linspace(0.0, 2.0, 81, dtype=torch.float64)
    gt, pred = _step(times, 1.0), _step(times, 1.25)
    r = switch_lag(times, pred, gt, fps=8.0)
    assert r["lag_s"] == pytest.approx(0.25, abs=0.026)  # one sample of 0.025 s
    assert r["lag_frames"] == pytest.approx(r["lag_s"] * 8.0)
    assert r["contrast_captured"] == pytest.approx(1.0)


def test_switch_lag_of_half_contrast_ramp():
    times = torch.linspace(0.0, 2.0, 201, dtype=torch.float64)
    gt = _step(times, 1.0)
    # a linear ramp from 10 to sqrt(10) between 0.5 and 1.5 s: half the log contrast,
    # centred on the switch, 10-90 % width 0.8 s
    hi, lo = 10.0, math.sqrt(10.0)
    pred = torch.clamp(hi + (lo - hi) * (times - 0.5), min=lo, max=hi)
    r = switch_lag(times, pred, gt, fps=8.0)
    assert r["contrast_captured"] == pytest.approx(0.5, abs=1e-9)
    assert r["lag_s"] == pytest.approx(0.0, abs=0.011)
    assert r["width_10_90_s"] == pytest.approx(0.8, abs=0.011)


def test_flat_prediction_has_no_crossing():
    times = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    r = step_response(times, torch.ones_like(times))
    assert r["t50"] is None and r["log_contrast"] == 0.0


# ---------------------------------------------------------------------------------------
# Scoring
# ---------------------------------------------------------------------------------------
def _lamp_map(h=16):
    d = equirect_directions(h)
    return 0.1 + 50.0 * (d[..., 1] > 0.9).float()[..., None] * torch.tensor([1.0, 0.9, 0.8])


def test_score_probe_scale_invariance_and_failures():
    gt = _lamp_map()
    preds = {"same": gt.clone(), "scaled": 7.0 * gt, "flat": torch.ones_like(gt), "nan": gt.clone()}
    preds["nan"][0, 0, 0] = float("nan")
    s = score_probe(preds, gt, sphere_size=16)
    assert s["nan"] == {"non_finite": True}
    for name in ("same", "scaled"):
        for mat in ("diffuse", "matte", "mirror"):
            assert s[name][mat]["si_rmse"] == pytest.approx(0.0, abs=1e-5)
            assert s[name][mat]["angular_deg"] == pytest.approx(0.0, abs=1e-2)
    assert s["flat"]["mirror"]["si_rmse_rel"] > 0.1  # the lamp is missing


# ---------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------
def _entry(prep, cpu, q, err, group="paper", error=None):
    e = {"method": {"group": group, "prior": "reprojection"}, "error": error}
    if error is None:
        e.update(
            {
                "time": {"prepare_s": prep, "prepare_cpu_s": cpu, "query_ms": q, "query_cpu_ms": q},
                "metrics": {
                    m: {"si_rmse_rel": err, "angular_deg": 1.0, "nrmse": 0.1} for m in ("diffuse", "matte", "mirror")
                },
                "temporal": None,
                "extra": {},
            }
        )
    return e


def test_time_to_answer_adds_queries_and_bake():
    e = _entry(2.0, 1.5, 100.0, 0.1)
    e["extra"]["bake"] = {"seconds": 0.5, "cpu_seconds": 0.25}
    assert time_to_answer(e, 4) == pytest.approx(2.0 + 0.4 + 0.5)
    assert time_to_answer(e, 4, cpu=True) == pytest.approx(1.5 + 0.4 + 0.25)


def test_markdown_shows_given_numbers_errors_and_only_common_methods_in_headline():
    suites = {}
    for name in ("a", "b"):
        methods = {"mlp": _entry(2.0, 1.0, 10.0, 0.123456 if name == "a" else 0.3),
                   "broken": _entry(0, 0, 0, 0, error="ValueError: boom" if name == "b" else None)}
        suites[name] = {"suite": {"held_out_probes": [{}, {}]}, "methods": methods}
    results = {"mode": "quick", "note": "tiny", "machine": {}, "simulated": {"budget": {"base": {}}, "suites": suites}}
    md = markdown(results)
    headline = md.split("### Headline")[1].split("### Suite")[0]
    assert "| mlp |" in headline and "broken" not in headline  # failed on suite b
    assert "0.212" in headline  # mean of 0.123456 and 0.3
    assert "ERROR: ValueError: boom" in md


def test_every_table_row_has_one_cell_per_header():
    from bench.report import SUITE_HEADERS, headline_rows, suite_rows

    suites = {
        "a": {
            "suite": {"held_out_probes": [{}]},
            "methods": {"m": _entry(1.0, 1.0, 1.0, 0.5), "bad": _entry(0, 0, 0, 0, error="RuntimeError: x")},
        }
    }
    headers, rows = headline_rows({"suites": suites})
    assert rows and all(len(r) == len(headers) for r in rows)
    assert all(len(r) == len(SUITE_HEADERS) for r in suite_rows(suites["a"]))


def test_sanitize_makes_strict_json():
    doc = sanitize({"a": float("nan"), "b": (1, float("inf")), "c": torch.tensor([1.5])})
    assert json.loads(json.dumps(doc, allow_nan=False)) == {"a": None, "b": [1, None], "c": [1.5]}


def test_update_readme_replaces_only_the_named_block(tmp_path):
    from bench.report import readme_markers, update_readme

    main_start, main_end = readme_markers()
    b_start, b_end = readme_markers("draft-budget")
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{main_start}\nold main\n{main_end}\nmiddle\n{b_start}\nold b\n{b_end}\ntail\n")
    results = {"mode": "quick", "note": "n", "machine": {"git_commit": "abc"}, "total_wall_s": 1.0}
    assert update_readme(readme, results, "lightfield bench --quick --iterations 300", block="draft-budget")
    text = readme.read_text()
    assert "old main" in text and "old b" not in text and "--iterations 300" in text
    assert text.startswith("intro\n") and text.endswith("tail\n") and "middle" in text
    assert not update_readme(tmp_path / "missing.md", results, "x")


def test_panorama_table_shows_ratios_correlation_and_the_truth_row():
    from bench.real_panoramas import CONSTANT, FIELD, PRIOR, summarise
    from bench.report import panorama_markdown

    def image(field_si, corr):
        scores = {}
        for name, si in ((FIELD, field_si), (PRIOR, 0.5), (CONSTANT, 0.4)):
            scores[name] = {
                m: {"si_rmse": si, "si_rmse_rel": si, "angular_deg": 10 * si, "nrmse": 0.1}
                for m in ("diffuse", "matte", "mirror")
            }
        return {"seconds": {FIELD: 20.0, PRIOR: 0.1, CONSTANT: 0.0}, "scores": scores,
                "observed_corr": {FIELD: corr, PRIOR: 0.8, CONSTANT: 0.0, "truth": 0.95}}

    methods = summarise([image(0.2, 0.9), image(0.4, 0.7)])
    assert methods[FIELD]["vs_constant"]["diffuse_si_rmse_rel"] == pytest.approx(0.3 / 0.4)
    assert methods[FIELD]["vs_constant"]["diffuse_angular_deg"] == pytest.approx(3.0 / 4.0)
    assert methods[FIELD]["observed_corr"] == pytest.approx(0.8)
    assert methods[CONSTANT]["vs_constant"]["diffuse_si_rmse_rel"] == pytest.approx(1.0)
    md = "\n".join(panorama_markdown({"protocol": "p", "splits": {"dev": {"methods": methods}}}))
    rows = [line for line in md.splitlines() if line.startswith("| dev")]
    header = next(line for line in md.splitlines() if line.startswith("| split"))
    assert len(rows) == 4 and all(r.count("|") == header.count("|") for r in rows)
    assert "| dev | field | 2 | 20 | 0.750 [0.500, 1" in md and "truth (protocol ceiling)" in md  # with its interval
    assert next(r for r in rows if "mean-colour" in r).count("[") == 0  # the baseline has no interval


@pytest.mark.parametrize("mode", ["quick", "full"])
def test_every_bench_method_builds_its_config(mode):
    """Each core and sweep method's overrides apply to the draft preset (a malformed override
    surfaced only after a long bench run, as a per-method ERROR row)."""
    from bench.methods import core_methods, sweep_methods
    from bench.run import BenchOptions, resolve_mode

    budget = resolve_mode(BenchOptions(quick=mode == "quick", iterations=600)).budget()
    methods = core_methods() + sweep_methods(budget)
    assert len({m.name for m in methods}) == len(methods)
    configs = {m.name: m.config(budget.base) for m in methods if m.family == "field"}
    assert configs["abl-no-lattice"].field.room_lattice == () and configs["mlp"].field.room_lattice
    assert configs["abl-no-free-probes"].distill.envmap_probe_count == configs["mlp"].distill.envmap_probe_count
    assert configs["abl-no-view-fit"].field.view_detail_heights == ()
    assert hash(tuple(methods))  # frozen, hashable methods (the runner keys on them)
