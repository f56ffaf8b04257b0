"""The dependency rules of docs/architecture.md, read from the source with ast (every import,
including those inside functions): HTTP and Celery adapters never import each other, the
library never imports the service side, the layers of core point one way, and module-level
imports form no cycle."""
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
    "core.priors": ("core.engine",),
    "core.fields": ("core.engine", "core.priors", "core.capture"),
    # inside core.fields: components <- kinds <- stored (docs/architecture.md)
    "core.fields.components": ("core.fields.kinds", "core.fields.stored"),
    "core.fields.kinds": ("core.fields.stored",),
    "core.capture": ("core.engine", "core.priors", "core.fields"),
    "core.io": ("core.engine", "core.priors", "core.fields", "core.capture"),
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports(path: Path, module_level_only: bool = False, type_checking: bool = False) -> set[str]:
    """Absolute names of the modules `path` imports (relative imports resolved); module_level_only:
    not those inside functions nor, unless `type_checking`, those under `if TYPE_CHECKING:`."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if module_level_only and (isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
                                      or (_is_type_checking(child) and not type_checking)):
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
