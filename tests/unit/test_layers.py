"""The layering of the code base, checked by reading every module's imports.

The house has three floors: the SDK (``clients/robocloud``) at the bottom, the service
framework (``services/common``) on it, and the services on top. Imports only go down, never
sideways between services (they talk over HTTP), and there is no import cycle anywhere.
Inside a service, only its web modules (the app and its routes) know the web framework, and
they reach the service's storage only through its domain modules.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.procs import REPO

ROOTS = {"robocloud": REPO / "clients" / "robocloud", "services": REPO / "services"}
WEB_FRAMEWORKS = ("fastapi", "starlette", "uvicorn")

WEB_MODULES = {
    "services.common": {"app", "auth", "bodies", "middleware", "responses", "runner", "server"},
    "services.cas": {"__main__", "app", "gateway", "kubo"},
    "services.ledger": {"__main__", "app"},
    "services.storage": {"__main__", "app", "records_api", "bags_api", "knowledge_api"},
    "services.broker": {"__main__", "app"},
    "services.fl": {"__main__", "app"},
}
"""Per package, the modules allowed to import the web framework; all others are domain code."""

STORAGE_MODULES = {
    "services.cas": {"services.cas.blockstore", "services.cas.pins"},
    "services.ledger": {
        "services.ledger.chaindb",
        "services.ledger.chain",
        "services.ledger.index",
    },
}
"""Per service, the modules that touch files or the chain: its web modules never import them."""


@dataclass(frozen=True)
class Import:
    module: str
    target: str
    line: int


def module_name(path: Path) -> str:
    for package, root in ROOTS.items():
        if path.is_relative_to(root):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            return ".".join((package, *parts))
    raise ValueError(path)


def source_files() -> Iterator[Path]:
    for root in ROOTS.values():
        yield from sorted(root.rglob("*.py"))


def imports_of(path: Path) -> list[Import]:
    """Every import in the file, inside functions and ``if TYPE_CHECKING:`` blocks too.

    An import only the type checker follows still ties the two modules' designs together.
    """
    module = module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[Import] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.extend(Import(module, alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base]) if base else ".".join(anchor)
            for alias in node.names:
                # ``from package import submodule`` needs the submodule, not the package.
                submodule = f"{base}.{alias.name}"
                found.append(
                    Import(module, submodule if submodule in MODULES else base, node.lineno)
                )
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    return found


MODULES = {module_name(path) for path in source_files()}
ALL_IMPORTS = [entry for path in source_files() for entry in imports_of(path)]


def internal(target: str) -> str | None:
    """The project module an import names (``a.b.c`` may be module ``a.b`` and name ``c``)."""
    while target:
        if target in MODULES:
            return target
        target = target.rpartition(".")[0]
    return None


def _is_under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_the_sdk_never_imports_services_or_the_web_framework() -> None:
    offending = [
        entry
        for entry in ALL_IMPORTS
        if _is_under(entry.module, "robocloud")
        and (
            _is_under(entry.target, "services")
            or any(_is_under(entry.target, web) for web in WEB_FRAMEWORKS)
        )
    ]
    assert offending == []


def test_services_never_import_each_other_and_common_never_imports_a_service() -> None:
    offending = []
    for entry in ALL_IMPORTS:
        if not _is_under(entry.module, "services") or not _is_under(entry.target, "services"):
            continue
        source = ".".join(entry.module.split(".")[:2])
        target = ".".join(entry.target.split(".")[:2])
        if target not in (source, "services.common") and target != "services":
            offending.append(entry)
    assert offending == []


@pytest.mark.parametrize("package", sorted(WEB_MODULES))
def test_only_web_modules_import_the_web_framework(package: str) -> None:
    offending = [
        entry
        for entry in ALL_IMPORTS
        if entry.module.rpartition(".")[0] == package
        and entry.module.rpartition(".")[2] not in WEB_MODULES[package]
        and any(_is_under(entry.target, web) for web in WEB_FRAMEWORKS)
    ]
    assert offending == []


@pytest.mark.parametrize("package", sorted(STORAGE_MODULES))
def test_routes_reach_storage_only_through_the_domain(package: str) -> None:
    web = {f"{package}.{name}" for name in WEB_MODULES[package]}
    offending = [
        entry
        for entry in ALL_IMPORTS
        if entry.module in web and internal(entry.target) in STORAGE_MODULES[package]
    ]
    assert offending == []


def test_there_is_no_import_cycle() -> None:
    graph: dict[str, set[str]] = {module: set() for module in MODULES}
    for entry in ALL_IMPORTS:
        target = internal(entry.target)
        if target is not None and target != entry.module:
            graph[entry.module].add(target)
    cycles = [component for component in strongly_connected(graph) if len(component) > 1]
    assert cycles == []


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm, iteratively (the graph is small, but recursion is for nobody)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, edges = work[-1]
            advanced = False
            for target in edges:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(sorted(graph[target]))))
                    advanced = True
                    break
                if target in on_stack:
                    low[node] = min(low[node], index[target])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                components.append(sorted(component))
    return components


def test_the_cycle_finder_finds_cycles() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert [c for c in strongly_connected(graph) if len(c) > 1] == [["a", "b", "c"]]
