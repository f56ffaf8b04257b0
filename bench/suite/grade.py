"""The job's quality grade (core.engine.self_check) as the suites' per-capture tables show it beside
each score: the grade, "-> constant map" when the fallback answered (core.engine.fallback), "–"
for a job without the check (an older artefact, a row rescored from a report made before it)."""
from __future__ import annotations


def job_grade(meta: dict) -> str:
    """The grade cell of a job from its artefact's lightfield.json."""
    quality = meta.get("quality") if isinstance(meta.get("quality"), dict) else {}
    grade = quality.get("grade")
    if not grade:
        return "–"
    return f"{grade} -> constant map" if quality.get("fallback") else grade
