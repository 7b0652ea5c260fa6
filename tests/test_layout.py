"""The package's layout is its architecture: no import circle, and each layer imports only the layers below it.

Read from the source with ``ast`` (every import statement, wherever it sits, except ``if TYPE_CHECKING:`` blocks
and ``__main__`` entry points), so the rules hold for imports inside functions too.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).parents[1]
SOURCES = {"dust_rl": "dust_rl", "envs": "dust_rl.envs", "agents": "dust_rl.agents"}  # folder -> package
LAYERS = {"dust_rl.storage", "dust_rl.runtime", "dust_rl.agents", "dust_rl.envs", "dust_rl.data", "dust_rl.evaluate",
          "dust_rl.train", "dust_rl.rl", "dust_rl.bench", "dust_rl.diagnose"}
# Packages (second name level) that a package may not import: the layers above it. The keys and the typed errors
# are below every layer; storage (files on disk, checkpoints among them) is below the agents and the envs.
FORBIDDEN = {
    "dust_rl.keys": LAYERS,
    "dust_rl.errors": LAYERS,
    "dust_rl.agents": {"dust_rl.envs", "dust_rl.data", "dust_rl.train", "dust_rl.evaluate", "dust_rl.rl",
                       "dust_rl.bench", "dust_rl.diagnose", "dust_rl.runtime"},
    "dust_rl.envs": {"dust_rl.agents", "dust_rl.data", "dust_rl.train", "dust_rl.evaluate", "dust_rl.rl",
                     "dust_rl.bench", "dust_rl.diagnose"},
    "dust_rl.storage": {"dust_rl.agents", "dust_rl.envs", "dust_rl.data", "dust_rl.train", "dust_rl.evaluate",
                        "dust_rl.rl", "dust_rl.bench", "dust_rl.diagnose"},
    "dust_rl.data": {"dust_rl.train", "dust_rl.evaluate", "dust_rl.rl", "dust_rl.bench", "dust_rl.diagnose"},
    "dust_rl.evaluate": {"dust_rl.train", "dust_rl.rl", "dust_rl.bench"},
    "dust_rl.train": {"dust_rl.rl", "dust_rl.bench"},
}
# Inside the agents, what each subpackage may import of the agents besides itself. The frozen encoders and the trunk
# read only the config (size caps, DustConfig); the heads read the encoders' outputs too. None imports the policy,
# the factory or the package's top level, which put them together.
AGENT_PARTS = {
    "dust_rl.agents.encoders": {"dust_rl.agents.config"},
    "dust_rl.agents.model": {"dust_rl.agents.config"},
    "dust_rl.agents.heads": {"dust_rl.agents.config", "dust_rl.agents.encoders"},
}


def modules() -> dict[str, pathlib.Path]:
    found = {}
    for folder, package in SOURCES.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = [p for p in path.relative_to(ROOT / folder).with_suffix("").parts if p != "__init__"]
            if parts[-1:] != ["__main__"]:
                found[".".join([package, *parts])] = path
    return found


def runtime_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Import statements outside ``if TYPE_CHECKING:`` blocks."""
    skipped = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
               and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING" for n in ast.walk(node)}
    return [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom) and id(n) not in skipped]


def import_graph() -> dict[str, set[str]]:
    found = modules()
    graph: dict[str, set[str]] = {name: set() for name in found}
    for name, path in found.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in runtime_imports(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = node.module if node.level == 0 else ".".join(p for p in (base, node.module) if p)
                targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in found else module for a in node.names]
            graph[name] |= {t for t in targets if t in found and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def package_of(module: str) -> str:
    return ".".join(module.split(".")[:2])


def within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    packages: dict[str, set[str]] = {}
    for name, targets in graph.items():
        packages.setdefault(package_of(name), set()).update(
            package_of(t) for t in targets if package_of(t) != package_of(name))
    for targets in list(packages.values()):
        for target in targets:
            packages.setdefault(target, set())
    return packages


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_no_module_imports_itself_back(graph):
    assert cycles(graph) == []


def test_no_package_imports_itself_back(graph):
    assert cycles(package_graph(graph)) == []


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layers_import_only_downwards(graph, package):
    upward = sorted((name, target) for name, targets in graph.items() if package_of(name) == package
                    for target in targets if package_of(target) in FORBIDDEN[package])
    assert upward == []


@pytest.mark.parametrize("part", sorted(AGENT_PARTS))
def test_agent_parts_import_only_what_they_build_on(graph, part):
    allowed = {part, *AGENT_PARTS[part]}
    members = [name for name in graph if within(name, part)]
    stray = sorted((name, target) for name in members for target in graph[name]
                   if within(target, "dust_rl.agents") and not any(within(target, a) for a in allowed))
    assert len(members) > 1 and stray == []


def test_the_checks_see_a_circle():
    """The graph reader finds a circle hidden in a function body and a relative import."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    tree = ast.parse("def f():\n    from .x import y\nif TYPE_CHECKING:\n    import z\n")
    assert [type(n).__name__ for n in runtime_imports(tree)] == ["ImportFrom"]
