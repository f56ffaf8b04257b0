"""Shared arguments and helpers of the commands that query one probe of a stored light field
(envmap, sh, cubemap, gltf, usdz, sequence). Not a command itself."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


def parse_position(text: str) -> tuple[float, float, float]:
    """'X,Y,Z' (metres) -> three finite floats; argparse reports the error as a usage error."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"--x must be three finite numbers 'X,Y,Z' in metres, got {text!r}")
    return values  # type: ignore[return-value]


def add_probe_arguments(p: argparse.ArgumentParser, time: bool = True) -> None:
    p.add_argument("artefact", metavar="OUT", help="artefact directory written by `lightfield estimate -o OUT`")
    p.add_argument("--x", required=True, type=parse_position, metavar="X,Y,Z", help="probe position, world metres")
    if time:
        p.add_argument("--t", type=float, default=None, metavar="SEC",
                       help="seconds from the first frame (required when the field varies over time)")
    p.add_argument("--fast", action="store_true",
                   help="answer from the baked grid next to the artefact (baked on first use; approximate)")


def check_output(path: Path, fmt: str, allowed: tuple[str, ...]) -> str | None:
    """An error message when the file name's extension disagrees with the format, else None."""
    suffix = path.suffix.lower().lstrip(".")
    if suffix and suffix != fmt:
        hint = f" (formats: {', '.join(allowed)})" if suffix not in allowed else ""
        return f"-o {path} has extension .{suffix} but the format is {fmt}{hint}: rename the file or change --format"
    return None


class Probe:
    """A loaded artefact answering env map queries, exact or from its baked grid."""

    def __init__(self, artefact_dir, fast: bool = False):
        from core.fields.stored.artefact import LightFieldArtefact

        self.artefact = LightFieldArtefact.load(artefact_dir)
        self.fast = fast
        self._baked = None

    def envmap(self, x, t, height: int):
        if self.fast:
            from core.fields.stored.bake import load_or_bake

            self._baked = self._baked or load_or_bake(self.artefact)
            return self._baked.envmap(x, t, height)
        return self.artefact.envmap(x, t, height)

    @property
    def grade(self) -> dict:
        """The job's grade and share seen vs filled (core.export.schema.AnswerGrade) for the exports."""
        from core.export.schema import AnswerGrade

        return AnswerGrade.of(self.artefact.meta).model_dump()

    @property
    def id(self) -> str:
        from core.export.metadata import artefact_id

        return artefact_id(self.artefact.meta)


def extrapolated(flags: dict) -> list[str]:
    return [axis for axis, key in (("x", "extrapolated_x"), ("t", "extrapolated_t")) if flags[key]]


def flags_model(flags: dict):
    """The field's {'extrapolated_x', 'extrapolated_t'} as the products' Flags model."""
    from core.export.schema import Flags

    return Flags(x=bool(flags["extrapolated_x"]), t=bool(flags["extrapolated_t"]))


def warn_extrapolated(flags: dict) -> None:
    axes = extrapolated(flags)
    if axes:
        print(f"warning: query outside the estimated {' and '.join(axes)} range; the answer is extrapolated",
              file=sys.stderr)


def run_guarded(body) -> int:
    """Run `body()`; artefact, query and media errors print `error: ...` and exit 2."""
    from core.fields.stored.artefact import ArtefactError, QueryError
    from core.io.limits import MediaError

    try:
        return body()
    except (ArtefactError, QueryError, MediaError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def print_json(doc) -> None:
    print(json.dumps(doc))
