"""The layers point one way: no import circle among the repository's packages, ``api`` and ``worker`` never
import each other, and ``voxe_core`` (the library) imports no service package and no web, queue or database library.

Read from the source (ast), so every import counts: module level, inside functions (lazy), under
``if TYPE_CHECKING``, relative, and ``importlib.import_module`` / ``__import__`` with a literal name.
Alembic migrations are left out (alembic loads them by path, nothing imports them).
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SERVICE_PACKAGES = ("api", "worker", "voxe_service", "voxe_client")
# What "a plain library: no web, queue or database code" rules out for voxe_core.
SERVICE_LIBRARIES = ("fastapi", "starlette", "uvicorn", "celery", "kombu", "redis", "sqlalchemy", "alembic",
                     "boto3", "botocore", "pydantic_settings", "psycopg")
LAZY_CLIENT_ALLOWED = {"voxe_core.cli.service"}  # `voxe sweep` talks to the service through voxe_client


@dataclass(frozen=True)
class Import:
    importer: str  # dotted module name
    target: str  # dotted name as written (resolved when relative)
    lazy: bool  # inside a function body
    line: int


def package_modules(root: Path = REPO) -> dict[str, Path]:
    """Dotted name -> file of every module of every top-level package (a folder with ``__init__.py``)."""
    modules = {}
    for package in sorted(p for p in root.iterdir() if (p / "__init__.py").is_file()):
        for path in package.rglob("*.py"):
            if "migrations" in path.relative_to(root).parts:
                continue
            name = ".".join(path.relative_to(root).with_suffix("").parts)
            modules[name.removesuffix(".__init__")] = path
    return modules


def imports_of(name: str, path: Path) -> list[Import]:
    """Every import of module ``name`` (absolute targets), lazy ones marked."""
    is_package = path.name == "__init__.py"
    found: list[Import] = []

    def resolve(module: str | None, level: int) -> str:
        if level == 0:
            return module or ""
        base = name.split(".") if is_package else name.split(".")[:-1]
        base = base[: len(base) - (level - 1)]
        return ".".join(base + ([module] if module else []))

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.extend(Import(name, a.name, lazy, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                module = resolve(child.module, child.level)
                found.append(Import(name, module, lazy, child.lineno))
                found.extend(Import(name, f"{module}.{a.name}", lazy, child.lineno) for a in child.names)
            elif (isinstance(child, ast.Call) and child.args and isinstance(child.args[0], ast.Constant)
                  and isinstance(child.args[0].value, str)
                  and ((isinstance(child.func, ast.Name) and child.func.id in ("__import__", "import_module"))
                       or (isinstance(child.func, ast.Attribute) and child.func.attr == "import_module"))):
                found.append(Import(name, child.args[0].value, lazy, child.lineno))
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), False)
    return found


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the repository modules it imports."""
    return {m: {i.target for i in imports_of(m, p) if i.target in modules and i.target != m} for m, p in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
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
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(10_000, limit))
    try:
        for v in sorted(graph):
            if v not in index:
                connect(v)
    finally:  # (left raised, it let test_cli's JSON nested 5000 deep parse, which that test needs refused)
        sys.setrecursionlimit(limit)
    return found


def top(name: str) -> str:
    return name.split(".", 1)[0]


# ---------------------------------------------------------------------------------- the checker itself
def test_the_checker_finds_lazy_relative_and_dynamic_circles(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.b import thing\n")
    (pkg / "b.py").write_text("def f():\n    from . import a\n")  # lazy and relative
    (pkg / "c.py").write_text("import importlib\nimportlib.import_module('pkg.sub.d')\n")
    (pkg / "sub" / "d.py").write_text("from ..c import x\n")  # relative two levels up
    (pkg / "e.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import a\n")
    (pkg / "migrations").mkdir()
    (pkg / "migrations" / "env.py").write_text("from pkg.a import thing\n")  # alembic's: not counted
    modules = package_modules(tmp_path)
    assert set(modules) == {"pkg", "pkg.a", "pkg.b", "pkg.c", "pkg.e", "pkg.sub", "pkg.sub.d"}
    graph = import_graph(modules)
    assert graph["pkg.e"] == {"pkg", "pkg.a"}
    assert circles(graph) == [["pkg.a", "pkg.b"], ["pkg.c", "pkg.sub.d"]]
    assert [i.lazy for i in imports_of("pkg.b", modules["pkg.b"])] == [True, True]


# ---------------------------------------------------------------------------------- the repository
PACKAGES = ("voxe_core", "voxe_client", "voxe_service", "api", "worker")


def test_every_package_is_checked():
    """Each package is found, not only no unknown one: a package without ``__init__.py`` (a namespace package, which
    still imports) had dropped out of every check below, and they passed on it unread."""
    assert {top(m) for m in package_modules()} == set(PACKAGES)


@pytest.mark.parametrize("folder, row", [("voxe_core", "`voxe_core/`"), ("voxe_core/guidance", "`voxe_core/`"),
                                         ("voxe_core/refine", "`voxe_core/`"), ("voxe_service", "`voxe_service/`"),
                                         ("worker", "`api/`, `worker/`")])
def test_the_readmes_layout_names_every_module(folder, row):
    """The README's Layout row of the library, the service core and the workers names each of their modules: the
    service core's row had left out six (webhooks, quotas and progress among them), the library's ten."""
    layout = (REPO / "README.md").read_text().split("\n## Layout\n\n", 1)[1].split("\n\n", 1)[0]
    cells = {line.split(" | ", 1)[0].removeprefix("| "): line for line in layout.splitlines()[2:]}
    named = set(re.findall(r"`(\w+)`", cells[row]))
    modules = {path.stem for path in (REPO / folder).glob("*.py")} - {"__init__", "__main__"}
    assert modules <= named, f"README's Layout row {row} does not name {sorted(modules - named)} of {folder}/"


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_circle_touches_the_package(package):
    found = [c for c in circles(import_graph(package_modules())) if any(top(m) == package for m in c)]
    assert not found, "import circles (lazy imports count): " + "; ".join(" <-> ".join(c) for c in found)


def test_api_and_worker_never_import_each_other():
    modules = package_modules()
    crossing = [f"{i.importer} -> {i.target} (line {i.line})"
                for m, p in modules.items() if top(m) in ("api", "worker")
                for i in imports_of(m, p) if top(i.target) in ("api", "worker") and top(i.target) != top(m)]
    assert not crossing, "api and worker import each other: " + "; ".join(sorted(crossing))


def test_the_library_imports_no_service_package_and_no_web_queue_or_database_library():
    modules = package_modules()
    wrong = []
    for m, p in modules.items():
        if top(m) != "voxe_core":
            continue
        for i in imports_of(m, p):
            target = top(i.target)
            if target == "voxe_client" and m in LAZY_CLIENT_ALLOWED and i.lazy:
                continue
            if target in SERVICE_PACKAGES or target in SERVICE_LIBRARIES:
                wrong.append(f"{m} -> {i.target} (line {i.line}{', lazy' if i.lazy else ''})")
    assert not wrong, "voxe_core must not import the service or its libraries: " + "; ".join(wrong)


def test_the_torch_free_modules_load_no_torch():
    """Settings, job schemas and ``voxe --help`` read constants and presets without torch or diffusers."""
    code = ("import sys, voxe_core.constants, voxe_core.presets, voxe_core.guidance, voxe_core.cli\n"
            "heavy = sorted(m for m in ('torch', 'diffusers', 'transformers') if m in sys.modules)\n"
            "assert not heavy, heavy\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
