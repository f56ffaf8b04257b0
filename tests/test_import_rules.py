"""The dependency rules of docs/architecture.md, read from the source with ast (every import,
including those inside functions): HTTP and Celery adapters never import each other, the
library never imports the service side, the layers of core point one way (the modules at the
top of core/ import none of its packages), and no import that runs, at module level or inside
a function, closes a cycle between files."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "jobs", "service", "worker", "cli", "bench")

# importer prefix -> module prefixes it must not import
FORBIDDEN = {
    "service": ("worker",),
    "worker": ("service",),
    "jobs": ("service", "worker", "cli", "bench"),
    "core": ("service", "worker", "jobs", "cli", "bench"),
    "core.engine": ("core.export", "core.sim", "core.training"),
    "core.priors": ("core.engine", "core.export", "core.sim"),
    "core.fields": ("core.engine", "core.priors", "core.capture", "core.tracking", "core.sim", "core.export"),
    # inside core.fields: components <- kinds <- stored (docs/architecture.md)
    "core.fields.components": ("core.fields.kinds", "core.fields.stored"),
    "core.fields.kinds": ("core.fields.stored",),
    "core.capture": ("core.engine", "core.priors", "core.fields", "core.export", "core.sim"),
    "core.tracking": ("core.engine", "core.priors", "core.fields", "core.capture", "core.export", "core.sim"),
    "core.io": ("core.engine", "core.priors", "core.fields", "core.capture", "core.tracking", "core.export",
                "core.sim"),
    "core.export": ("core.engine", "core.priors", "core.capture", "core.tracking", "core.sim", "core.training"),
}
CORE = REPO / "core"
# core/*.py (conventions, camera, envmap, sh, lights, ...): the bottom layer, under every package of core
CORE_PACKAGES = tuple(sorted(f"core.{p.name}" for p in CORE.iterdir() if (p / "__init__.py").is_file()))


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports(path: Path, module_level_only: bool = False, type_checking: bool = False,
            runtime_only: bool = False) -> set[str]:
    """Absolute names of the modules `path` imports (relative imports resolved); module_level_only:
    not those inside functions nor, unless `type_checking`, those under `if TYPE_CHECKING:`;
    runtime_only: every import that runs (inside functions too), none under `if TYPE_CHECKING:`."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if module_level_only and (isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
                                      or (_is_type_checking(child) and not type_checking)):
                continue
            if runtime_only and _is_type_checking(child):
                continue
            if isinstance(child, ast.Import):
                found.update(alias.name for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
                    anchor = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                found.add(base)
                found.update(f"{base}.{alias.name}" for alias in child.names)  # `from pkg import submodule`
            visit(child)

    visit(tree)
    return found


def sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py") if "results" not in p.parts)


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


@pytest.mark.parametrize("importer", sorted(FORBIDDEN))
def test_layers_import_only_downwards(importer):
    bad = []
    for path in sources():
        if not _within(module_name(path), importer):
            continue
        for name in imports(path):
            bad += [f"{module_name(path)} imports {name}" for banned in FORBIDDEN[importer] if _within(name, banned)]
    assert not bad, "\n".join(bad)


def test_the_modules_at_the_top_of_core_import_none_of_its_packages():
    """core/sh.py, core/lights.py, core/insertion.py ...: what every package builds on (an export
    layout or a capture helper they need lives in the package, or moves down to them)."""
    bad = []
    for path in sorted(CORE.glob("*.py")):
        bad += [f"{module_name(path)} imports {name}" for name in imports(path)
                if any(_within(name, package) for package in CORE_PACKAGES)]
    assert CORE_PACKAGES and not bad, "\n".join(bad)


def test_no_import_that_runs_closes_a_cycle_between_files():
    """Imports inside functions count: one there only hides a cycle from import time."""
    modules = {module_name(p): p for p in sources()}
    graph = {m: {n for n in imports(p, runtime_only=True) if n in modules and n != m} for m, p in modules.items()}
    assert not cycles(graph), cycles(graph)


def test_module_level_imports_have_no_cycle():
    modules = {module_name(p): p for p in sources()}
    graph = {m: {n for n in imports(p, module_level_only=True) if n in modules and n != m} for m, p in modules.items()}
    assert not cycles(graph), cycles(graph)


def test_fields_imports_have_no_cycle_even_for_type_checking():
    """core.fields: components <- kinds (registry <- config <- base <- mlp, grid, trunk) <- stored,
    with no loop closed by a type-checking import either."""
    modules = {module_name(p): p for p in sources() if _within(module_name(p), "core.fields")}
    graph = {m: {n for n in imports(p, module_level_only=True, type_checking=True) if n in modules and n != m}
             for m, p in modules.items()}
    assert not cycles(graph), cycles(graph)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module."""
    index, low, stack, on_stack, found, counter = {}, {}, [], set(), [], [0]

    def strongconnect(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            strongconnect(v)
    return found


def test_the_rules_see_imports_inside_functions(tmp_path):
    source = tmp_path / "x.py"
    source.write_text("def f():\n    from worker.runner import JobRunner\n")
    assert "worker.runner" in imports(source) and "worker.runner" not in imports(source, module_level_only=True)
    assert "worker.runner" in imports(source, runtime_only=True)


def test_runtime_imports_leave_out_type_checking_only_ones(tmp_path):
    source = tmp_path / "x.py"
    source.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import jobs.store\n")
    assert "jobs.store" in imports(source) and "jobs.store" not in imports(source, runtime_only=True)
