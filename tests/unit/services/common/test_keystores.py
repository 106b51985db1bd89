"""A service's own key: generated once, then read back; two first starts agree on one key."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from robocloud.errors import KeystoreError
from robocloud.identity import Identity
from services.common.keystores import service_key


def test_the_first_start_generates_a_key_the_next_reads(tmp_path: Path) -> None:
    path = tmp_path / "keys" / "node.json"
    first = service_key(path, "secret")
    assert json.loads(path.read_text())["address"].lower() == first.address[2:].lower()
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    assert service_key(path, "secret").address == first.address


def test_two_first_starts_on_one_directory_run_with_the_same_key(tmp_path: Path) -> None:
    """Both find no keystore and both generate (scrypt takes long enough for both to be in
    it); the one that saves second must not fail the service's start nor run with a key
    nobody kept."""
    path = tmp_path / "keys" / "node.json"
    barrier = threading.Barrier(2)
    found: list[Identity] = []

    def start() -> None:
        barrier.wait()
        found.append(service_key(path, "secret"))

    starts = [threading.Thread(target=start) for _ in range(2)]
    for each in starts:
        each.start()
    for each in starts:
        each.join()
    kept = Identity.load(path, "secret")
    assert [identity.address for identity in found] == [kept.address] * 2
    assert sorted(p.name for p in path.parent.iterdir()) == ["node.json"]


def test_a_wrong_passphrase_is_refused_and_the_keystore_kept(tmp_path: Path) -> None:
    path = tmp_path / "node.json"
    service_key(path, "secret")
    before = path.read_bytes()
    with pytest.raises(KeystoreError):
        service_key(path, "other")
    assert path.read_bytes() == before
