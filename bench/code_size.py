"""The size of the engine (core/engine, core/priors, core/fields) at git revisions: physical lines
and Python statements (AST nodes: a count that line wrapping and comments do not move).

    python -m bench.code_size [REV ...]      # default: HEAD

Issue 44 asks for fewer lines there than when it was filed (19d9417); a formatting pass
(e646052, wrapping at 120 characters) added hundreds of lines and no statement, so both counts
are printed.
"""
from __future__ import annotations

import argparse
import ast
import subprocess

ENGINE_DIRS = ("core/engine", "core/priors", "core/fields")


def source_size(source: str) -> tuple[int, int]:
    """(physical lines, statements) of one Python source."""
    return source.count("\n"), sum(isinstance(node, ast.stmt) for node in ast.walk(ast.parse(source)))


def size_at(rev: str, dirs=ENGINE_DIRS) -> tuple[int, int]:
    """(physical lines, statements) of every .py file under `dirs` at git revision `rev`."""
    names = subprocess.run(["git", "ls-tree", "-r", "--name-only", rev, *dirs], capture_output=True, text=True,
                           check=True).stdout.split()
    lines = statements = 0
    for name in names:
        if name.endswith(".py"):
            src = subprocess.run(["git", "show", f"{rev}:{name}"], capture_output=True, text=True, check=True).stdout
            n, s = source_size(src)
            lines, statements = lines + n, statements + s
    return lines, statements


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("revs", nargs="*", default=["HEAD"])
    args = p.parse_args(argv)
    print("| revision | lines | statements |\n|---|---|---|")
    for rev in args.revs:
        lines, statements = size_at(rev)
        print(f"| {rev} | {lines} | {statements} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
