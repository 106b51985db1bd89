"""js-ipfs-unixfs's importer (the reference ``ipfs add -r``), run by Node on the same trees."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REFERENCE = Path(__file__).parent


def node() -> str:
    """Node, with the reference installed beside it; a test without them skips (fails in CI)."""
    found = shutil.which("node")
    if found is None or not (REFERENCE / "node_modules").is_dir():
        if os.environ.get("CI"):
            pytest.fail("js reference missing: run `npm ci --prefix tests/reference`")
        pytest.skip("js reference missing (npm ci --prefix tests/reference)")
    return found


def reference_cid(directory: Path, *args: str) -> str:
    """The root CID the reference gives ``directory``; ``args`` as import-dir.mjs takes them."""
    done = subprocess.run(
        [node(), str(REFERENCE / "import-dir.mjs"), str(directory), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    return done.stdout.strip()


def write_tree(root: Path, files: dict[str, bytes]) -> Path:
    """``root`` holding ``files`` (paths relative to it), parents made as needed."""
    for path, data in files.items():
        target = root / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    return root
