"""The committed artifacts are what the sources compile to, and the SDK ships the same ABIs."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
CONTRACTS = REPO / "contracts"
BUILD = CONTRACTS / "build"
SDK_ABI = REPO / "clients" / "robocloud" / "abi"
SOLC = CONTRACTS / "node_modules" / "solc" / "package.json"


def artifacts() -> dict[str, dict[str, object]]:
    return {path.stem: json.loads(path.read_text()) for path in sorted(BUILD.glob("*.json"))}


def test_every_source_has_artifacts_built_from_its_current_text() -> None:
    """Cheap guard without Node: the artifacts record the SHA-256 of the source they came from."""
    built = artifacts()
    sources = {path.name: path for path in CONTRACTS.glob("*.sol")}
    assert {"Registry", "AnchorLog"} <= built.keys()
    assert {a["sourceName"] for a in built.values()} == sources.keys()
    for name, artifact in built.items():
        text = sources[str(artifact["sourceName"])].read_bytes()
        assert artifact["sourceSha256"] == hashlib.sha256(text).hexdigest(), name
        assert str(artifact["bytecode"]).startswith("0x60"), name


def test_sdk_ships_the_same_abis() -> None:
    built = artifacts()
    shipped = {path.stem: json.loads(path.read_text()) for path in SDK_ABI.glob("*.json")}
    assert shipped.keys() == built.keys()
    for name, artifact in built.items():
        assert shipped[name] == {"contractName": name, "abi": artifact["abi"]}


def compiler_available() -> bool:
    return shutil.which("node") is not None and SOLC.is_file()


def test_recompiling_reproduces_the_committed_artifacts(tmp_path: Path) -> None:
    """Recompile with the pinned solc-js; CI (CI or ROBOCLOUD_REQUIRE_SOLC set) must have it."""
    if not compiler_available():
        if os.environ.get("CI") or os.environ.get("ROBOCLOUD_REQUIRE_SOLC"):
            pytest.fail("solc-js missing: run `npm ci --prefix contracts` before the tests")
        pytest.skip("node or contracts/node_modules missing (npm ci --prefix contracts)")
    assert json.loads(SOLC.read_text())["version"] == "0.8.26"
    build, abi = tmp_path / "build", tmp_path / "abi"
    subprocess.run(
        ["node", str(CONTRACTS / "compile.mjs"), "--build-dir", str(build), "--abi-dir", str(abi)],
        check=True,
        capture_output=True,
        timeout=240,
    )
    for fresh_dir, committed_dir in [(build, BUILD), (abi, SDK_ABI)]:
        fresh = {p.name: p.read_bytes() for p in fresh_dir.glob("*.json")}
        committed = {p.name: p.read_bytes() for p in committed_dir.glob("*.json")}
        assert fresh.keys() == committed.keys()
        for name, content in fresh.items():
            assert content == committed[name], f"{committed_dir.name}/{name} is stale: recompile"
