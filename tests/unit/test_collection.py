"""Every test module imports under a name of its own.

In importlib mode pytest names a module inside a package after its chain of packages (up to
the first folder without ``__init__.py``) and reuses a module already imported under that
name. Two test files whose chains end alike (``storage/test_knowledge.py`` under both unit
and integration) therefore ran the first file twice and the second not at all, silently.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from tests.procs import REPO

TESTS = REPO / "tests"


def import_name(path: Path) -> str:
    """The name pytest's importlib mode gives the module at ``path``."""
    parts = [path.stem]
    folder = path.parent
    while (folder / "__init__.py").exists():
        parts.insert(0, folder.name)
        folder = folder.parent
    return ".".join(parts) if folder != path.parent else str(path.relative_to(REPO))


def test_no_two_test_modules_share_an_import_name() -> None:
    modules = [
        path
        for path in TESTS.rglob("*.py")
        if "node_modules" not in path.parts and path.name.startswith(("test_", "conftest"))
    ]
    by_name: defaultdict[str, list[str]] = defaultdict(list)
    for path in modules:
        by_name[import_name(path)].append(str(path.relative_to(REPO)))
    assert len(modules) > 100
    assert {name: paths for name, paths in by_name.items() if len(paths) > 1} == {}
