"""The design documents stay design documents (issue 64): each keeps within its size budget, and
README.md and docs/engine.md carry no measurement log: no commit hashes, no dates, no CPU or host
names. Figures live in the generated results pages under bench/results/ (which name the command,
machine, commit and date of each run); the documents state a headline and link to them. Dated
history goes to docs/notes/ or is left to git.

The checks read the whole file, link targets included: a results file whose name carries a date
or a commit is linked through an index page that names it (e.g. bench/results/cv/README.md)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

KB = 1000  # the budgets are decimal kilobytes (16 KB = 16,000 bytes)
BUDGETS = {"README.md": 16 * KB, "docs/engine.md": 40 * KB, "bench/README.md": 30 * KB}
NO_LOG = ["README.md", "docs/engine.md"]

# A commit hash: a word-bounded run of 7-40 lowercase hex digits with at least one digit and one
# letter (so neither a number such as 2026120 nor a word such as "defaced" counts).
HASH = re.compile(r"(?<![0-9A-Za-z_])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![0-9A-Za-z_])")
DATE = re.compile(r"(?<!\d)\d{4}-\d{2}-\d{2}(?!\d)")
HOST = re.compile(r"\b(?:Xeon|EPYC|Ryzen|Threadripper|Core i[3579]|Apple M[1-4])\b", re.I)


def size_violations(path: Path, budget: int) -> list[str]:
    size = len(path.read_bytes())
    return [f"{size} bytes, over its budget of {budget}"] if size > budget else []


def log_violations(text: str) -> list[str]:
    """What makes a design document a measurement log: each hit with its line number."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for kind, pattern in (("commit hash", HASH), ("date", DATE), ("CPU/host name", HOST)):
            found += [f"line {number}: {kind} {m.group(0)!r}" for m in pattern.finditer(line)]
    return found


@pytest.mark.parametrize("name", sorted(BUDGETS))
def test_document_within_its_budget(name):
    problems = size_violations(REPO / name, BUDGETS[name])
    assert not problems, f"{name}: {problems[0]}: move measurement narrative to docs/notes/ or a results page"


@pytest.mark.parametrize("name", NO_LOG)
def test_document_holds_no_hashes_dates_or_hosts(name):
    problems = log_violations((REPO / name).read_text())
    assert not problems, (f"{name} reads as a measurement log (state the headline, link the results page, "
                          f"put the history in docs/notes/): {problems}")


@pytest.mark.parametrize("text", [
    "since 588fba5 the draft", "run at 2db76112cef735fcc06ae9064c77c2da5fb18681.", "(at d75db8c)",
    "measured on 2026-12-07", "2 Intel Xeon cores", "an AMD EPYC host", "a Ryzen laptop",
    "an Intel Core i7", "an Apple M2", "[file](results/steps-400-2026-12-07.md)",
])
def test_a_log_line_is_caught(text):
    assert log_violations(text)


@pytest.mark.parametrize("text", [
    "diffuse si-RMSE 0.4934 (0.49x), 1e-3 floor, 2 cores", "a decade of radiance, defaced", "1234567 frames",
    "SHA-256 recorded at write", "x264 with MB-tree off", "the core idea", "ab12cd",
])
def test_design_prose_passes(text):
    assert not log_violations(text)


def test_an_oversized_document_is_caught(tmp_path):
    doc = tmp_path / "README.md"
    doc.write_bytes(b"x" * (16 * KB + 1))
    assert size_violations(doc, 16 * KB)
    doc.write_bytes(b"x" * (16 * KB))
    assert not size_violations(doc, 16 * KB)
