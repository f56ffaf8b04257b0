"""Every relative link in the docs points at a file that is in the repository: a renamed
benchmark result or a moved module must not leave a figure whose source cannot be opened."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", REPO / "bench" / "README.md", *sorted((REPO / "docs").glob("*.md")),
        *sorted((REPO / "bench" / "results").rglob("README.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def relative_links(doc: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)  # code blocks hold no links
    return [t for t in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]


@pytest.mark.parametrize("doc", DOCS, ids=lambda d: str(d.relative_to(REPO)))
def test_every_relative_link_resolves(doc):
    missing = [t for t in relative_links(doc) if not (doc.parent / t.split("#", 1)[0]).exists()]
    assert not missing, f"{doc.relative_to(REPO)} links to files that are not there: {missing}"


def test_a_broken_link_is_caught(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("see [a](a.md), [web](https://example.org), [here](#top) and\n```\n[not](a link)\n```\n")
    assert relative_links(doc) == ["a.md"]
