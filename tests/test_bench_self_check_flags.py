"""bench.self_check_flags' rates and page from rows (the jobs themselves run in tests/test_fail_safe.py)."""
from __future__ import annotations


def _row(capture, ratios, grade, fallback=None):
    return {"yaw": 0.0, "capture": capture, "vs_constant": ratios, "grade": grade, "fallback": fallback,
            "pairs_disagreeing": 0, "stage": None, "cpu_s": 4.0, "self_check_s": 0.2}


def test_the_rates_count_flags_among_the_worse_and_the_better_captures():
    from bench.self_check_flags import flag_rates, markdown

    rows = [_row("a", [1.5, 0.9], "partly explained", "reason"), _row("b", [1.3, 1.3], "explained"),
            _row("c", [0.5, 0.6], "explained"), _row("d", [0.7, 0.7], "partly explained"),
            _row("e", [0.9, 1.0], "explained")]
    rates = flag_rates(rows)
    assert rates == {"worse_than_1.2x": [1, 2], "better_than_0.8x": [1, 2], "in_between": 1}
    page = markdown({"command": "python -m bench.self_check_flags", "machine": {"cpu_model": "X"}, "rooms": 1,
                     "rows": rows, "rates": rates, "wall_s": 60.0, "cpu_s_median": 4.0, "self_check_s_median": 0.2})
    assert "A SMALL SAMPLE" in page and "flagged: **1 of 2**" in page
    assert "| 0 | a | 1.50 / 0.90 | – | partly explained | constant map | 0 | – |" in page
