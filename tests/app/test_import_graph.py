"""No import circles in ``app``, ``leap_core`` and ``lab`` (function-local imports included) or in ``web``'s
modules, and the imports between the packages go one way: ``lab`` → ``app`` → ``leap_core``.

A circle hidden behind an import inside a function works until someone moves that import to the top of
its module (or imports the modules in the other order), so the check is static: it reads every module's
imports with ``ast``, wherever they stand, and looks for cycles in the module graph. Imports under
``if TYPE_CHECKING:`` never run and are left out (annotations may refer both ways).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("app", "leap_core", "lab")
WEB = ROOT / "web"

_JS_IMPORT = re.compile(
    r"""(?:^|;)\s*(?:import|export)\s+(?:[^'";]*?\s+from\s+)?["']([^"']+\.js)["']"""
    r"""|\bimport\(\s*["']([^"']+\.js)["']\s*\)""",
    re.MULTILINE,
)
"""A static ``import``/``export ... from`` of a ``.js`` module, or a dynamic ``import("...js")``."""


def module_files(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Dotted module name → file for every ``.py`` file under the packages (``pkg/__init__.py`` → ``pkg``)."""
    out: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imported_names(tree: ast.AST, module: str, is_package: bool) -> list[str]:
    """Absolute dotted names a module's import statements can load (``from a import b`` gives ``a.b``,
    which resolves to module ``a.b`` or, for a name defined in ``a``, to ``a``)."""
    names: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module.split(".") if is_package else module.split(".")[:-1]
                package = package[: len(package) - node.level + 1]
                base = ".".join([*package, base] if base else package)
            names.append(base)
            names.extend(f"{base}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return names


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module → the modules of the set that importing it may import (directly).

    Importing ``a.b.c`` also runs ``a/__init__`` and ``a/b/__init__``; those parent packages count, except
    the importing module's own parents (already being imported when it runs).
    """
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        targets: set[str] = set()
        for imported in _imported_names(ast.parse(path.read_text()), module, path.name == "__init__.py"):
            name = imported
            while name and name not in modules:
                name = name.rpartition(".")[0]
            parts = name.split(".") if name else []
            for i in range(1, len(parts) + 1):
                target = ".".join(parts[:i])
                if target in modules and target != module and not module.startswith(target + "."):
                    targets.add(target)
        graph[module] = targets
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (``[a, b, ..., a]``) per strongly connected group of modules that import each other."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return [_cycle_in(graph, set(group)) for group in groups]


def _cycle_in(graph: dict[str, set[str]], group: set[str]) -> list[str]:
    """A concrete cycle through the group's first module (breadth-first back to it)."""
    start = min(group)
    parents: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & group):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(parents[path[-1]])
                    return [start, *reversed(path[:-1]), start]
                if w not in parents:
                    parents[w] = v
                    nxt.append(w)
        frontier = nxt
    raise AssertionError("a strongly connected group always has a cycle")


def test_app_and_leap_core_have_no_import_circles() -> None:
    modules = module_files(ROOT, PACKAGES)
    assert {"app.main", "app.jobs.worker", "app.viewer.session", "leap_core.config"} <= set(modules)
    cycles = find_cycles(import_graph(modules))
    assert cycles == [], "import circles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def _importers_of(graph: dict[str, set[str]], package: str, among: str) -> dict[str, list[str]]:
    """Module of ``among`` → the modules of ``package`` it imports (static, function-local included)."""
    out = {}
    for module, targets in graph.items():
        if module == among or module.startswith(among + "."):
            hits = sorted(t for t in targets if t == package or t.startswith(package + "."))
            if hits:
                out[module] = hits
    return out


def test_the_product_never_imports_the_lab_and_leap_core_never_the_app() -> None:
    # The lab (research code: fitting the simulated labeler, Table 1) sits beside the product and imports
    # it; leap_core and app must run without it, and leap_core without the app.
    modules = module_files(ROOT, PACKAGES)
    assert {"lab", "lab.paper_labeler", "lab.table1"} <= set(modules)
    graph = import_graph(modules)
    assert _importers_of(graph, "lab", "leap_core") == {}
    assert _importers_of(graph, "lab", "app") == {}
    assert _importers_of(graph, "app", "leap_core") == {}
    # The lab reaches the app only for its command line (python -m lab).
    assert set(_importers_of(graph, "app", "lab")) == {"lab.__main__"}


def test_a_planted_import_of_the_lab_is_found_behind_a_function(tmp_path: Path) -> None:
    files = {
        "leap_core/__init__.py": "",
        "leap_core/stage.py": "def run():\n    from lab.paper_labeler import X\n    return X\n",
        "lab/__init__.py": "",
        "lab/paper_labeler.py": "import leap_core.stage\nX = 1\n",
    }
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    graph = import_graph(module_files(tmp_path, ("leap_core", "lab")))
    assert _importers_of(graph, "lab", "leap_core") == {"leap_core.stage": ["lab", "lab.paper_labeler"]}


def _package(tmp_path: Path, files: dict[str, str]) -> dict[str, Path]:
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return module_files(tmp_path, ("pkg",))


def test_a_planted_circle_is_found_even_behind_a_function_local_import(tmp_path: Path) -> None:
    modules = _package(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/config.py": "def check():\n    from pkg.demo import make\n    return make()\n",
            "pkg/demo.py": "from pkg import services\n\ndef make():\n    return services.x\n",
            "pkg/services.py": "from .config import check\nx = 1\n",
            "pkg/leaf.py": "import pkg.config\n",
        },
    )
    cycles = find_cycles(import_graph(modules))
    assert cycles == [["pkg.config", "pkg.demo", "pkg.services", "pkg.config"]]


@pytest.mark.parametrize(
    ("panel", "expected"),
    [
        ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.session import Session\n", []),
        (
            "import typing\nif typing.TYPE_CHECKING:\n    pass\nelse:\n    from pkg import session\n",
            [["pkg.panel", "pkg.session", "pkg.panel"]],
        ),
        ("def build():\n    from pkg.session import Session\n", [["pkg.panel", "pkg.session", "pkg.panel"]]),
    ],
)
def test_type_only_imports_do_not_count_but_runtime_ones_do(
    tmp_path: Path, panel: str, expected: list[list[str]]
) -> None:
    files = {"pkg/__init__.py": "", "pkg/panel.py": panel, "pkg/session.py": "from pkg.panel import x\n"}
    modules = _package(tmp_path, files)
    assert find_cycles(import_graph(modules)) == expected


def test_a_package_init_importing_its_modules_is_no_circle(tmp_path: Path) -> None:
    modules = _package(
        tmp_path,
        {
            "pkg/__init__.py": "from pkg.sub import thing\n",
            "pkg/sub/__init__.py": "from pkg.sub.impl import thing\n",
            "pkg/sub/impl.py": "from pkg.sub import helpers\nthing = helpers\n",
            "pkg/sub/helpers.py": "",
        },
    )
    assert find_cycles(import_graph(modules)) == []


def web_import_graph(web: Path) -> dict[str, set[str]]:
    """Module of the web UI (its path under ``web``, e.g. ``viewer/nav.js``) → the modules of ``web`` it
    imports, statically or dynamically (``./x.js`` relative to it, ``/x.js`` from the web root it is
    served from)."""
    graph: dict[str, set[str]] = {}
    root = web.resolve()
    for path in sorted(web.rglob("*.js")):
        targets: set[str] = set()
        for match in _JS_IMPORT.finditer(path.read_text()):
            spec = match.group(1) or match.group(2)
            target = root / spec.lstrip("/") if spec.startswith("/") else path.resolve().parent / spec
            targets.add(target.resolve().relative_to(root).as_posix())
        graph[path.resolve().relative_to(root).as_posix()] = targets
    return {module: targets & graph.keys() for module, targets in graph.items()}


def test_web_modules_have_no_import_circles() -> None:
    # A module imported by the module it imports runs before that module's body: what it reads from it is
    # not set yet (the viewer page's feature modules once deferred their first request for that reason).
    graph = web_import_graph(WEB)
    assert {"viewer/overlay.js", "viewer/nav.js", "viewer/viewer-api.js"} <= graph.keys()
    assert "viewer/viewer-api.js" in graph["viewer/nav.js"]
    cycles = find_cycles(graph)
    assert cycles == [], "import circles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_a_planted_web_import_circle_is_found(tmp_path: Path) -> None:
    files = {
        "api.js": "export function api() {}\n",
        "viewer/overlay.js": 'import { api } from "/api.js";\nimport "./nav.js";\nexport const id = 1;\n',
        "viewer/nav.js": 'import { bind } from "./keys.js"; import { id } from "./overlay.js";\n',
        "viewer/keys.js": 'export function bind() {}\nconst later = () => import("./tools.js");\n',
        "viewer/tools.js": 'export * from "./keys.js";\n',
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    graph = web_import_graph(tmp_path)
    assert graph["viewer/overlay.js"] == {"api.js", "viewer/nav.js"}
    assert find_cycles(graph) == [
        ["viewer/keys.js", "viewer/tools.js", "viewer/keys.js"],
        ["viewer/nav.js", "viewer/overlay.js", "viewer/nav.js"],
    ]
