"""The IPFS fixtures in ../shared/data/ipfs (sources in its vectors.json and SOURCES.md)."""

from __future__ import annotations

import hashlib
import json
from functools import cache
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.ciphers import Cipher, algorithms

from robocloud.unixfs import ImportParams
from tests.procs import SHARED_DATA

IPFS = SHARED_DATA / "ipfs"
PROFILES = {
    "v0": ImportParams(cid_version=0, raw_leaves=False),
    "v0-rawleaves": ImportParams(cid_version=0, raw_leaves=True),
    "v1-raw-256k": ImportParams(cid_version=1, raw_leaves=True),
    "v1-noraw-256k": ImportParams(cid_version=1, raw_leaves=False),
    "v1-2025": ImportParams.from_options(profile="unixfs-v1-2025"),
}
MAX_GENERATED = 64 * 1024 * 1024  # the 1 GiB vectors are for the benchmark, not the suite


@cache
def vectors() -> dict[str, Any]:
    return dict(json.loads((IPFS / "vectors.json").read_text()))


def chacha20_bytes(seed: str, size: int) -> bytes:
    """kubo's deterministic test data: the ChaCha20 keystream under sha256(seed)."""
    key = hashlib.sha256(seed.encode()).digest()
    return Cipher(algorithms.ChaCha20(key, b"\0" * 16), mode=None).encryptor().update(b"\0" * size)


def vector_input(vector: dict[str, Any]) -> bytes | None:
    if "path" in vector:
        return (IPFS / vector["path"]).read_bytes()
    if vector["generator"] == "chacha20" and int(vector["size"]) <= MAX_GENERATED:
        return chacha20_bytes(vector["seed"], int(vector["size"]))
    return None


def file_cases() -> list[tuple[str, str, str]]:
    """``(input name, profile, expected CID)`` for every vector this suite can reproduce."""
    return [
        (vector["input"], expected["profile"], expected["cid"])
        for vector in vectors()["vectors"]
        if "path" in vector
        or (vector["generator"] == "chacha20" and int(vector["size"]) <= MAX_GENERATED)
        for expected in vector["expected"]
    ]


def input_named(name: str) -> bytes:
    for vector in vectors()["vectors"]:
        if vector["input"] == name:
            data = vector_input(vector)
            assert data is not None
            return data
    raise KeyError(name)


def car_path(relative: str) -> Path:
    return IPFS / relative
