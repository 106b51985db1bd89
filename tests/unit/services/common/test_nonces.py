"""The replay guard remembers nonces across restarts and forgets them only when harmless."""

from __future__ import annotations

import time
from pathlib import Path

from services.common.nonces import NonceStore

ADDRESS = "0x2c7536E3605D9C16a7a3D7b1898e529396a65c23"


def test_nonce_is_accepted_once_per_address(tmp_path: Path) -> None:
    store = NonceStore(tmp_path / "nonces.log", window_s=300)
    now = int(time.time())
    assert store.use(ADDRESS, "n" * 16, now)
    assert not store.use(ADDRESS, "n" * 16, now)
    assert not store.use(ADDRESS.lower(), "n" * 16, now)
    assert store.use("0x" + "1" * 40, "n" * 16, now)


def test_nonces_survive_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=300)
    now = int(time.time())
    assert store.use(ADDRESS, "a" * 16, now)
    store.close()
    reopened = NonceStore(path, window_s=300)
    assert not reopened.use(ADDRESS, "a" * 16, now)


def test_expired_nonces_are_forgotten_and_the_journal_compacts(tmp_path: Path) -> None:
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=1, compact_after=4)
    old = int(time.time()) - 10
    for i in range(4):
        assert store.use(ADDRESS, f"old-nonce-{i:06d}", old)
    assert len(store) == 0
    fresh = int(time.time())
    assert store.use(ADDRESS, "fresh-nonce-0001", fresh)
    assert path.read_text().count("\n") <= 2
    store.close()
    assert len(NonceStore(path, window_s=1)) == 1


def test_torn_last_line_is_ignored(tmp_path: Path) -> None:
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=300)
    assert store.use(ADDRESS, "b" * 16, int(time.time()))
    store.close()
    with path.open("a") as handle:
        handle.write("0xdead torn")
    assert len(NonceStore(path, window_s=300)) == 1
