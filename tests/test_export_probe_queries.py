"""core.export.probe_queries: the one home of what `lightfield sh` / `unity` and GET /sh / /unity
share, so the two adapters cannot drift apart."""
from __future__ import annotations

import argparse

import pytest

from core.export.probe_queries import UNITY_GRID_AXIS_MAX, parse_grid


def test_parse_grid_reads_three_counts_and_names_the_rule():
    assert parse_grid("3,2,3") == (3, 2, 3)
    assert parse_grid(f"1,{UNITY_GRID_AXIS_MAX},1") == (1, UNITY_GRID_AXIS_MAX, 1)
    for bad in ("3,2", "3,2,x", "0,1,1", f"1,1,{UNITY_GRID_AXIS_MAX + 1}", ""):
        with pytest.raises(ValueError, match=r"grid must be three integers in 1\.\.64 'NX,NY,NZ'"):
            parse_grid(bad)


def test_the_cli_and_the_api_refuse_a_bad_grid_with_the_same_words():
    from cli.unity import _counts as cli_counts
    from service.errors import InvalidInput
    from service.routes.lightfield import _counts as api_counts

    with pytest.raises(argparse.ArgumentTypeError) as cli_error:
        cli_counts("3,2")
    with pytest.raises(InvalidInput) as api_error:
        api_counts("3,2")
    assert str(cli_error.value) == "--" + str(api_error.value)
    assert api_error.value.code == "invalid_query"
