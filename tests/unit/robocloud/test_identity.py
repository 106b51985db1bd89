"""Keys at rest: encrypted keystores that round-trip and refuse what they should."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from robocloud.errors import KeystoreError
from robocloud.identity import Identity
from tests.fresh_interpreter import printed_by

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


@pytest.mark.parametrize("address", ["zz", "0x12", "g" * 40])
def test_a_keystore_with_a_malformed_address_is_a_keystore_error(
    tmp_path: Path, address: str
) -> None:
    """eth_utils' ValueError escaped as a traceback from ``robocloud keys show``."""
    path = tmp_path / "key.json"
    path.write_text(json.dumps({"address": address}))
    with pytest.raises(KeystoreError, match="malformed address"):
        Identity.keystore_address(path)


def test_a_save_that_fails_midway_leaves_no_keystore_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The keystore was created under its name and then written, so a failed write (a full
    disk) left an empty file that made the next ``keys new`` refuse to overwrite it and
    ``keys show`` call it unreadable."""
    path = tmp_path / "robot.json"

    def disk_full(_: int) -> None:
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as patched:
        patched.setattr("robocloud.identity.os.fsync", disk_full)
        with pytest.raises(OSError, match="No space left"):
            Identity.generate().save(path, "pass", scrypt_n=FAST_SCRYPT)
    assert list(tmp_path.iterdir()) == []
    Identity.generate().save(path, "pass", scrypt_n=FAST_SCRYPT)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_loading_the_signing_library_keeps_the_recursion_limit() -> None:
    """Loaded on first use, inside a CLI command run under CPython's 1,000, eth-account's
    py_ecc raised the limit to 100,000 for the rest of that command."""
    probe = (
        "import sys\n"
        "from robocloud.identity import Identity\n"
        "sys.setrecursionlimit(1000)\n"
        "Identity.generate()\n"
        "print('py_ecc' in sys.modules, sys.getrecursionlimit())\n"
    )
    assert printed_by(probe).split() == ["True", "1000"]
