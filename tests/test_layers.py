"""The layers of the code, checked on its source: which package may import which.

Every module's imports are read from its syntax tree (at any depth, inside functions too), so
a lazy import cannot slip past. Each rule is one case; a failure names the rule and every
offending ``file:line``.
"""

from __future__ import annotations

import ast
import dataclasses
import itertools
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import ROOT

LIBRARY = ("server", "sim", "robot_agent", "recording", "factors", "schemas")
PROJECT = (*LIBRARY, "mrslam", "bench", "tests")
#: the server's algorithm groups: no I/O, no processes (docs/development.md)
SERVER_ALGORITHMS = ("server.slam", "server.planning", "server.control", "server.exploration",
                     "server.lookout", "server.fleet", "server.rendezvous", "server.command",
                     "server.knownmap")
#: what ``schemas/se2.py`` may import: the bottom of the stack, numbers only
SE2_ALLOWED = ("__future__", "math", "typing", "collections.abc", "numpy")


@dataclass(frozen=True)
class Import:
    module: str          # the importing module, e.g. ``server.runtime.daemon``
    path: str            # its file, relative to the checkout
    line: int
    name: str            # the module it imports, absolute: ``schemas.config_loading``
    at_import_time: bool  # not inside a function, nor under ``if TYPE_CHECKING:``
    members: tuple[str, ...] = ()  # ``from name import a, b``: a and b (modules, or not)

    def __str__(self) -> str:
        return f"{self.path}:{self.line} imports {self.name}"


def under(name: str, *packages: str) -> bool:
    """Whether the dotted ``name`` is one of ``packages`` or inside one of them."""
    return any(name == p or name.startswith(p + ".") for p in packages)


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_in(source: str, module: str, path: str, is_package: bool = False) -> list[Import]:
    """Every import statement of one module's source, relative imports made absolute."""
    tree = ast.parse(source, filename=path)
    package = module if is_package else module.rpartition(".")[0]
    out: list[Import] = []

    def visit(node: ast.AST, import_time: bool) -> None:
        for child in ast.iter_child_nodes(node):
            deferred = isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda) or (
                isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test))
            now = import_time and not deferred
            if isinstance(child, ast.Import):
                out.extend(Import(module, path, child.lineno, a.name, now) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parts = package.split(".")
                    anchor = parts[:len(parts) - child.level + 1]
                    base = ".".join([*anchor, *([base] if base else [])])
                out.append(Import(module, path, child.lineno, base, now,
                                  tuple(a.name for a in child.names)))
            visit(child, now)

    visit(tree, True)
    return out


def project_imports(root: Path = ROOT) -> list[Import]:
    out: list[Import] = []
    for package in PROJECT:
        for f in sorted((root / package).rglob("*.py")):
            if "__pycache__" in f.parts:
                continue
            rel = f.relative_to(root).as_posix()
            out += imports_in(f.read_text(encoding="utf-8"), module_name(f, root), rel,
                              f.name == "__init__.py")
    return out


@dataclass(frozen=True)
class Rule:
    name: str
    applies: Callable[[str], bool]   # to an importing module
    breaks: Callable[[str], bool]    # an imported name that breaks it

    def violations(self, imports: Iterable[Import]) -> list[Import]:
        return [i for i in imports if self.applies(i.module) and self.breaks(i.name)]


def _se2_breaks(name: str) -> bool:
    return not under(name, *SE2_ALLOWED)


RULES = [
    Rule("library code never imports the CLI package mrslam",
         lambda m: under(m, *LIBRARY), lambda n: under(n, "mrslam")),
    Rule("bench never imports tests",
         lambda m: under(m, "bench"), lambda n: under(n, "tests")),
    Rule("schemas imports nothing of the project outside schemas",
         lambda m: under(m, "schemas"),
         lambda n: under(n, *PROJECT) and not under(n, "schemas")),
    Rule("robot_agent never imports server, sim, factors, gtsam, open3d, skimage, scipy or "
         "numba",
         lambda m: under(m, "robot_agent"),
         lambda n: under(n, "server", "sim", "factors", "gtsam", "open3d", "skimage", "scipy",
                         "numba")),
    Rule("schemas/se2.py imports only " + ", ".join(SE2_ALLOWED),
         lambda m: m == "schemas.se2", _se2_breaks),
    Rule("factors never imports server, sim or robot_agent",
         lambda m: under(m, "factors"), lambda n: under(n, "server", "sim", "robot_agent")),
    # the server's groups (docs/development.md): runtime, offline and console around the core;
    # the core over commands, the fleet and its merging; those over the algorithms
    Rule("the server's core and algorithms never import its runtime, offline tools or console",
         lambda m: under(m, *SERVER_ALGORITHMS, "server.core"),
         lambda n: under(n, "server.runtime", "server.offline", "server.console")),
    Rule("only the server's runtime and console talk to Zenoh",
         lambda m: under(m, "server") and not under(m, "server.runtime", "server.console"),
         lambda n: under(n, "zenoh", "schemas.bus")),
    Rule("slam, planning and control never import exploration, the fleet, teams, commands or "
         "the core", lambda m: under(m, "server.slam", "server.planning", "server.control"),
         lambda n: under(n, "server.exploration", "server.lookout", "server.fleet",
                         "server.rendezvous", "server.command", "server.knownmap",
                         "server.core")),
    Rule("the offline tools run without a bus: never the node, the daemon or the cluster",
         lambda m: under(m, "server.offline"),
         lambda n: under(n, "server.runtime.node", "server.runtime.daemon",
                         "server.runtime.cluster", "server.console")),
]


def import_cycles(imports: Iterable[Import], package: str) -> list[list[Import]]:
    """Cycles among the modules of ``package`` through imports run when a module is loaded;
    each cycle as the imports that close it, one per strongly connected group."""
    imports = [i for i in imports if under(i.module, package) and i.at_import_time]
    modules = {i.module for i in imports}
    edges: dict[str, dict[str, Import]] = {m: {} for m in modules}
    for i in imports:
        if not under(i.name, package):
            continue
        # ``from pkg import mod`` loads the module ``pkg.mod``; ``from pkg.mod import f`` and
        # ``import pkg.mod`` load ``pkg.mod``
        targets = [t for t in (f"{i.name}.{m}" for m in i.members) if t in modules] or [i.name]
        for target in targets:
            if target in modules and target != i.module:
                edges[i.module].setdefault(target, i)
    cycles = []
    for group in _strongly_connected(edges):
        if len(group) > 1:
            cycles.append(_cycle_through(group, edges))
    return cycles


def _strongly_connected(edges: dict[str, dict[str, Import]]) -> Iterator[set[str]]:
    """Tarjan's algorithm (the graphs here are a few dozen nodes: recursion is fine)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    counter = itertools.count()

    def visit(v: str) -> Iterator[set[str]]:
        index[v] = low[v] = next(counter)
        stack.append(v)
        for w in edges[v]:
            if w not in index:
                yield from visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                group.add(w)
                if w == v:
                    break
            yield group

    for v in sorted(edges):
        if v not in index:
            yield from visit(v)


def _cycle_through(group: set[str], edges: dict[str, dict[str, Import]]) -> list[Import]:
    """One cycle inside a strongly connected group, as the imports along it."""
    start = min(group)
    path, seen, node = [], {start}, start
    while True:
        nxt = min(w for w in edges[node] if w in group)
        path.append(edges[node][nxt])
        if nxt == start or nxt in seen:
            return path[next(k for k, i in enumerate(path) if i.module == nxt):]
        seen.add(nxt)
        node = nxt


@pytest.fixture(scope="module")
def imports() -> list[Import]:
    return project_imports()


@pytest.mark.parametrize("rule", RULES, ids=[r.name for r in RULES])
def test_layer_rule(rule: Rule, imports: list[Import]) -> None:
    assert any(rule.applies(i.module) for i in imports), f"{rule.name}: no module it applies to"
    bad = rule.violations(imports)
    assert not bad, f"{rule.name}:\n" + "\n".join(f"  {i}" for i in bad)


@pytest.mark.parametrize("lazy", [False, True], ids=["module-level imports",
                                                    "imports inside functions too"])
def test_no_import_cycle_among_the_cli_modules(imports: list[Import], lazy: bool) -> None:
    """A cycle through imports inside functions loads, but still ties the two modules into
    one (report <-> figures did)."""
    if lazy:
        imports = [dataclasses.replace(i, at_import_time=True) for i in imports]
    cycles = import_cycles(imports, "mrslam")
    assert not cycles, "import cycles among mrslam modules:\n" + \
        "\n".join("  " + " -> ".join(str(i) for i in c) for c in cycles)


# -- the checker itself can fail -------------------------------------------------------------

def test_a_lazy_import_of_the_cli_from_library_code_is_caught() -> None:
    src = "import numpy\n\ndef run():\n    from mrslam.config import load_config\n"
    found = imports_in(src, "server.runtime.daemon", "server/runtime/daemon.py")
    bad = RULES[0].violations(found)
    assert [str(i) for i in bad] == ["server/runtime/daemon.py:4 imports mrslam.config"]
    assert not bad[0].at_import_time


def test_relative_imports_are_resolved_and_se2_may_import_only_numbers() -> None:
    src = "from __future__ import annotations\nimport math\nfrom . import keys\n"
    found = imports_in(src, "schemas.se2", "schemas/se2.py")
    assert [i.name for i in RULES[4].violations(found)] == ["schemas"]
    nested = imports_in("from ..bus import Bus\n", "server.slam.robot", "server/slam/robot.py")
    assert nested[0].name == "server.bus"


def test_a_cycle_is_found_and_a_lazy_import_does_not_close_one() -> None:
    a = imports_in("from mrslam.b import f\n", "mrslam.a", "mrslam/a.py")
    b = imports_in("import mrslam.a\n", "mrslam.b", "mrslam/b.py")
    (cycle,) = import_cycles(a + b, "mrslam")
    assert {str(i) for i in cycle} == {"mrslam/a.py:1 imports mrslam.b",
                                       "mrslam/b.py:1 imports mrslam.a"}
    lazy = imports_in("def g():\n    import mrslam.a\n", "mrslam.b", "mrslam/b.py")
    assert import_cycles(a + lazy, "mrslam") == []


def test_a_server_algorithm_importing_the_runtime_or_zenoh_is_caught() -> None:
    src = "from server.runtime.node import ServerNode\nimport zenoh\n"
    found = imports_in(src, "server.slam.robot", "server/slam/robot.py")
    broken = {r.name for r in RULES for _ in r.violations(found)}
    assert broken == {RULES[6].name, RULES[7].name}
