"""bench.code_size: statements do not move when a line is wrapped; lines do."""
from bench.code_size import source_size


def test_wrapping_a_call_adds_lines_and_no_statement():
    flat = "x = f(1, 2, 3)\nif x:\n    y = 2\n"
    wrapped = "x = f(\n    1,\n    2,\n    3,\n)\nif x:\n    y = 2\n"
    assert source_size(flat) == (3, 3)
    assert source_size(wrapped) == (7, 3)
