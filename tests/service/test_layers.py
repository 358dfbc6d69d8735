"""The shape of `service/`: every import goes down the declared layers (or sideways within one), no import cycle,
no module over `MAX_LINES` lines (docs/architecture.md, "Layers")."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVICE = Path(__file__).resolve().parents[2] / "service"
PACKAGE = "gmt.service"
MAX_LINES = 600
# Lowest first. A module may import from its own layer or a lower one, never from a higher one.
LAYERS: tuple[tuple[str, frozenset[str]], ...] = (
    (
        "foundations",
        frozenset(
            {
                "errors",
                "units",
                "memory",
                "logs",
                "keys",
                "ids",
                "activity",
                "observations",
                "records",
                "examples",
                "redis_connect",
            }
        ),
    ),
    ("config", frozenset({"settings", "limits", "metrics", "events", "views"})),
    (
        "store and engine",
        frozenset(
            {
                "sessions",
                "session_codec",
                "resp",
                "redis_connect",
                "redis_keys",
                "redis_scripts",
                "redis_local",
                "redis_commit",
                "redis_store",
                "registry",
                "model_state",
                "batcher",
                "admin",
            }
        ),
    ),
    ("core state", frozenset({"core_state"})),
    (
        "core parts",
        frozenset({"core_versions", "core_sessions", "core_acts", "core_recordings", "core_feeds"}),
    ),
    ("core", frozenset({"core"})),
    ("adapters", frozenset({"rest", "grpc", "console"})),
    ("entry points", frozenset({"server", "serve_cli", "cli"})),
)
# Layers whose modules must not import one another: the core's parts share state only through `Core`, and each
# adapter stands alone (REST and gRPC never import each other).
APART = {"core parts", "adapters"}


def _modules() -> dict[str, Path]:
    """Each module of `service/` by its name under `gmt.service` ("core", "rest.app", "console")."""
    out = {}
    for p in sorted(SERVICE.rglob("*.py")):
        parts = p.relative_to(SERVICE).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if parts:
            out[".".join(parts)] = p
    return out


def _type_only(tree: ast.Module) -> set[int]:
    """Line numbers of imports under `if TYPE_CHECKING:` (annotations only: never run)."""
    lines = set()
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.If)
            and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING"
        ):
            for sub in node.body:
                for n in ast.walk(sub):
                    lines.add(getattr(n, "lineno", -1))
    return lines


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """The `service/` modules `path` imports, at the top or inside a function (type-only imports aside)."""
    tree = ast.parse(path.read_text(), str(path))
    skip = _type_only(tree)
    names: set[str] = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)  # `from gmt.service import keys`
    found = set()
    for n in names:
        if n.startswith(PACKAGE + "."):
            rel = n[len(PACKAGE) + 1 :]
            while rel and rel not in modules:
                rel = rel.rpartition(".")[0]
            if rel:
                found.add(rel)
    return found


def _layer(module: str) -> int:
    top = module.split(".")[0]
    for i, (_, members) in enumerate(LAYERS):
        if top in members:
            return i
    raise AssertionError(
        f"service/{module.replace('.', '/')} is in no layer: add it to LAYERS (and architecture.md)"
    )


MODULES = _modules()
GRAPH = {m: _imports(p, MODULES) - {m} for m, p in MODULES.items()}


def test_every_module_has_a_layer() -> None:
    for m in MODULES:
        _layer(m)


def test_imports_go_down_the_layers() -> None:
    up = []
    for m, deps in GRAPH.items():
        for d in deps:
            lm, ld = _layer(m), _layer(d)
            if ld > lm:
                up.append(f"{m} ({LAYERS[lm][0]}) imports {d} ({LAYERS[ld][0]})")
            elif ld == lm and LAYERS[lm][0] in APART and m.split(".")[0] != d.split(".")[0]:
                up.append(f"{m} imports {d}: {LAYERS[lm][0]} stand apart")
    assert not up, "imports against the layers:\n" + "\n".join(sorted(up))


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of `graph` (a path that starts and ends at one module), or None."""
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                return path[path.index(d) :] + [d]
            if d not in state and (found := visit(d)):
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_no_import_cycle() -> None:
    cycle = _cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_cycle_between_packages() -> None:
    """rest, grpc and console as wholes: `rest.app` importing the console's routes that import `rest.routes` was
    one (the console's routes now live in `rest.console`)."""
    packages = {m.split(".")[0] for m in MODULES}
    graph = {p: set() for p in packages}
    for m, deps in GRAPH.items():
        graph[m.split(".")[0]].update(d.split(".")[0] for d in deps if d.split(".")[0] != m.split(".")[0])
    cycle = _cycle(graph)
    assert cycle is None, "package import cycle: " + " -> ".join(cycle)


def test_the_checks_see_what_they_check() -> None:
    """The parser finds imports of each form, and the cycle finder finds a cycle (else the tests above pass
    vacuously)."""
    assert {"errors", "ids", "views", "core_acts"} <= GRAPH["core"] | GRAPH["core_acts"]
    assert "keys" in GRAPH["metrics"]  # `from gmt.service import keys`
    assert "redis_store" in GRAPH["core"]  # imported inside a function
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


@pytest.mark.parametrize("path", sorted(SERVICE.rglob("*.py")), ids=lambda p: str(p.relative_to(SERVICE)))
def test_no_module_over_the_limit(path: Path) -> None:
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, (
        f"service/{path.relative_to(SERVICE)} has {n} lines (at most {MAX_LINES}): split it by job"
    )
