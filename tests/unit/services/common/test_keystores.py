"""A service's own key: generated once, then read back; two first starts agree on one key."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from robocloud.errors import KeystoreError
from robocloud.identity import STANDARD_SCRYPT_N, Identity
from services.common.keystores import (
    GENERATED_SECRET_SCRYPT_N,
    KeyPassphrase,
    key_passphrase,
    service_key,
)

SECRET = KeyPassphrase("secret", STANDARD_SCRYPT_N)


def test_the_first_start_generates_a_key_the_next_reads(tmp_path: Path) -> None:
    path = tmp_path / "keys" / "node.json"
    first = service_key(path, SECRET)
    assert json.loads(path.read_text())["address"].lower() == first.address[2:].lower()
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    assert service_key(path, SECRET).address == first.address


def test_two_first_starts_on_one_directory_run_with_the_same_key(tmp_path: Path) -> None:
    """Both find no keystore and both generate (scrypt takes long enough for both to be in
    it); the one that saves second must not fail the service's start nor run with a key
    nobody kept."""
    path = tmp_path / "keys" / "node.json"
    barrier = threading.Barrier(2)
    found: list[Identity] = []

    def start() -> None:
        barrier.wait()
        found.append(service_key(path, SECRET))

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
    service_key(path, SECRET)
    before = path.read_bytes()
    with pytest.raises(KeystoreError):
        service_key(path, KeyPassphrase("other", STANDARD_SCRYPT_N))
    assert path.read_bytes() == before


def scrypt_n(path: Path) -> int:
    return int(json.loads(path.read_text())["crypto"]["kdfparams"]["n"])


def test_a_configured_passphrase_gets_the_standard_cost_and_a_generated_secret_the_light(
    tmp_path: Path,
) -> None:
    """A generated secret is 256 random bits: stretching it bought no safety, only 1.2 s a
    start. A passphrase a person chose keeps the standard cost."""
    configured = key_passphrase("a person's passphrase", tmp_path / "unused.secret")
    service_key(tmp_path / "configured.json", configured)
    assert scrypt_n(tmp_path / "configured.json") == STANDARD_SCRYPT_N == 2**18
    assert not (tmp_path / "unused.secret").exists()

    generated = key_passphrase(None, tmp_path / "node.secret")
    assert generated.text == (tmp_path / "node.secret").read_text()
    assert len(generated.text) == 43, "token_urlsafe(32): 256 bits"
    assert oct((tmp_path / "node.secret").stat().st_mode & 0o777) == "0o600"
    key = service_key(tmp_path / "generated.json", generated)
    assert scrypt_n(tmp_path / "generated.json") == GENERATED_SECRET_SCRYPT_N == 2**12
    again = service_key(tmp_path / "generated.json", key_passphrase(None, tmp_path / "node.secret"))
    assert again.address == key.address
