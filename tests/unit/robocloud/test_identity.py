"""Keys at rest: encrypted keystores that round-trip and refuse what they should."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from robocloud.errors import KeystoreError
from robocloud.identity import Identity

FAST_SCRYPT = 2**10  # the default 2**18 costs about a second; the format is the same


def test_keystore_round_trips_and_is_private(tmp_path: Path) -> None:
    identity = Identity.generate()
    path = tmp_path / "keys" / "robot.json"
    identity.save(path, "correct horse", scrypt_n=FAST_SCRYPT)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    stored = json.loads(path.read_text())
    assert identity.account.key.hex().removeprefix("0x") not in path.read_text()
    assert stored["crypto"]["kdf"] == "scrypt"
    assert Identity.load(path, "correct horse").address == identity.address
    assert Identity.keystore_address(path) == identity.address


def test_wrong_passphrase_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "robot.json"
    Identity.generate().save(path, "right", scrypt_n=FAST_SCRYPT)
    with pytest.raises(KeystoreError, match="wrong passphrase"):
        Identity.load(path, "wrong")


def test_existing_key_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "robot.json"
    first = Identity.generate()
    first.save(path, "pass", scrypt_n=FAST_SCRYPT)
    with pytest.raises(KeystoreError, match="refusing to overwrite"):
        Identity.generate().save(path, "pass", scrypt_n=FAST_SCRYPT)
    assert Identity.load(path, "pass").address == first.address


def test_empty_passphrase_is_refused(tmp_path: Path) -> None:
    with pytest.raises(KeystoreError, match="empty passphrase"):
        Identity.generate().save(tmp_path / "robot.json", "")
    assert not (tmp_path / "robot.json").exists()


def test_missing_keystore_says_how_to_make_one(tmp_path: Path) -> None:
    with pytest.raises(KeystoreError, match="robocloud keys new"):
        Identity.load(tmp_path / "absent.json", "pass")


def test_did_names_chain_and_address() -> None:
    identity = Identity.generate()
    assert identity.did(1337) == f"did:pkh:eip155:1337:{identity.address}"


@pytest.mark.parametrize(
    ("document", "message"),
    [
        (b"[" * 100_000 + b"]" * 100_000, "nested deeper"),
        (b'["a list"]', "a keystore is a JSON object"),
        (b'{"crypto": {}}', "missing 'version'"),
        (
            b'{"version": 3, "crypto": {"kdf": "scrypt", "kdfparams": {"n": 16777216, "r": 8}}}',
            "beyond this SDK's bounds",
        ),
        (b'{"crypto": {"kdfparams": {"c": "many"}}}', "malformed key-derivation"),
    ],
    ids=["nested", "not-an-object", "missing-fields", "huge-scrypt", "odd-params"],
)
def test_a_hostile_keystore_is_a_keystore_error(
    tmp_path: Path, document: bytes, message: str
) -> None:
    path = tmp_path / "key.json"
    path.write_bytes(document)
    with pytest.raises(KeystoreError, match=message):
        Identity.load(path, "pw")
