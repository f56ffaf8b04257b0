"""`lightfield` console script. Each subcommand lives in its own module under cli/ and
exposes `HELP`, `add_arguments(parser)` and `run(args) -> int`. Command modules keep heavy
imports (torch, fastapi, celery) inside `run` so `lightfield --help` stays fast."""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = [
    "demo",
    "simulate",
    "estimate",
    "envmap",
    "sh",
    "cubemap",
    "gltf",
    "usd",
    "sequence",
    "unity",
    "arkit",
    "preview",
    "serve",
    "stream",
    "worker",
    "bench",
    "train-prior",
    "prior",
]


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Appends '(default: X)' to an option's help when it has a value default (not None, not a
    flag such as --fast / --no-resume, not already mentioned in the help)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        flag = isinstance(action, (argparse._StoreConstAction, argparse._StoreTrueAction, argparse._StoreFalseAction,
                                   argparse._HelpAction, argparse._VersionAction))
        if ("%(default)" in text or "(default" in text or "default:" in text or default is None or flag
                or default == argparse.SUPPRESS or not action.option_strings):
            return text
        return f"{text} (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lightfield", description="Spatiotemporal indoor HDR lighting estimation.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        module_name = "cli." + name.replace("-", "_")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue  # command not built yet
            raise
        p = sub.add_parser(name, help=module.HELP, description=module.HELP, formatter_class=DefaultsHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
