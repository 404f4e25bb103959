"""The import layering of docs/development.md, read from the source (every import, the lazy ones
inside functions included; ``if TYPE_CHECKING:`` blocks are annotations only and skipped):
``cli → actions → {live, outputs, sim} → pipeline → geometry → the shared root modules``.
A module imports only from its own layer and the layers below; the wings live, outputs and sim
never import each other; and the command modules of cbh/actions import each other without a
cycle (issue 36: export.py and aviation.py imported each other; station.py reached up into
pipeline/config.py and live/service.py, a loop of five files)."""
from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

CBH = Path(__file__).resolve().parents[1] / "cbh"
CLI = Path(__file__).resolve().parents[1] / "cli"

#: Layer → rank; a module may import a layer of lower rank or its own layer (never a higher one,
#: never another layer of the same rank).
RANK = {"root": 0, "geometry": 1, "pipeline": 2, "live": 3, "outputs": 3, "sim": 3, "actions": 4, "cli": 5}


def _module(path: Path) -> str:
    parts = list(path.relative_to(CBH.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    if parts[0] == "cli":
        return "cli"
    return parts[1] if len(parts) > 1 and parts[1] in RANK else "root"  # cbh.errors, cbh.result, …


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return skip


def imports_of(path: Path, text: str | None = None) -> list[tuple[int, str]]:
    """(line, imported module) for every cbh/cli import in ``path`` (or ``text``, its source),
    relative ones resolved."""
    tree = ast.parse(path.read_text() if text is None else text, filename=str(path))
    skip = _type_checking_nodes(tree)
    package = _module(path) if path.name == "__init__.py" else _module(path).rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            out.append((node.lineno, name))
            out += [(node.lineno, f"{name}.{a.name}") for a in node.names]  # `from cbh import actions`
    return [(line, m.replace("cbh.cli", "cli", 1) if m.startswith("cbh.cli") else m) for line, m in out
            if m == "cbh" or m.startswith(("cbh.", "cli"))]


def _sources() -> list[Path]:
    return sorted(p for p in [*CBH.rglob("*.py"), *CLI.rglob("*.py")] if "cli" not in p.relative_to(CBH.parent).parts[1:2])


@functools.lru_cache(maxsize=None)
def _known(module: str) -> bool:
    """A module of the repository (``module`` or, for ``from m import name``, its parent)."""
    for cand in (module, module.rpartition(".")[0]):
        rel = CBH.parent / Path(*cand.split("."))
        if rel.with_suffix(".py").is_file() or (rel / "__init__.py").is_file():
            return True
    return False


@functools.lru_cache(maxsize=None)
def _imports_on_disk(path: Path) -> tuple[tuple[int, str], ...]:
    return tuple(imports_of(path))


def layer_violations(texts: dict[Path, str] | None = None) -> list[str]:
    """Every import of a higher layer or of a sibling wing (``texts``: sources to read instead)."""
    bad = []
    for path in _sources():
        here = _layer(_module(path))
        text = (texts or {}).get(path)
        for line, target in (_imports_on_disk(path) if text is None else imports_of(path, text)):
            if target == "cbh" or not _known(target):
                continue
            there = _layer(target)
            if there != here and RANK[there] >= RANK[here]:
                bad.append(f"{path.relative_to(CBH.parent)}:{line}: {here} imports {target} ({there})")
    return bad


def test_no_layer_imports_upwards_or_sideways():
    assert layer_violations() == []


@pytest.mark.parametrize("where, line, says", [
    ("geometry/station.py", "from cbh.pipeline.config import PipelineConfig", "geometry imports cbh.pipeline.config"),
    ("pipeline/run.py", "from cbh.outputs import export", "pipeline imports cbh.outputs"),
    ("outputs/maps.py", "from ..sim import render", "outputs imports cbh.sim"),
    ("live/service.py", "import cbh.actions.run", "live imports cbh.actions.run"),
])
def test_the_checker_sees_an_upward_or_sideways_import(where, line, says):
    """The test above can fail: a lazy import of a higher layer or a sibling wing is caught."""
    path = CBH / where
    src = path.read_text() + f"\n\ndef _up():\n    {line}\n"
    assert any(says in v for v in layer_violations({path: src}))


def _actions_graph() -> dict[str, set[str]]:
    graph = {}
    for path in sorted((CBH / "actions").glob("*.py")):
        mod = _module(path)
        graph[mod] = {t for _, t in imports_of(path) if t.startswith("cbh.actions.") and t != mod
                      and (CBH.parent / Path(*t.split("."))).with_suffix(".py").is_file()}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}

    def visit(node, trail):
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return trail[trail.index(nxt):] + [nxt] if nxt in trail else [node, nxt]
            if nxt not in state:
                found = visit(nxt, trail + [nxt])
                if found:
                    return found
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state:
            found = visit(start, [start])
            if found:
                return found
    return None


def test_actions_import_each_other_without_a_cycle():
    assert _cycle(_actions_graph()) is None


@pytest.mark.parametrize("graph, has_cycle", [({"a": {"b"}, "b": {"a"}}, True), ({"a": {"b"}, "b": {"c"}, "c": set()}, False),
                                              ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, True)])
def test_the_cycle_finder(graph, has_cycle):
    assert (_cycle(graph) is not None) == has_cycle
