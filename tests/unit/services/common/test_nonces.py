"""The replay guard remembers nonces across restarts and forgets them only when harmless."""

from __future__ import annotations

import errno
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from services.common import durable
from services.common.nonces import NonceQuotaExceeded, NonceStore, NonceStoreFull

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


def test_each_nonce_of_an_address_is_separate(tmp_path: Path) -> None:
    store = NonceStore(tmp_path / "nonces.log", window_s=300)
    now = int(time.time())
    nonces = [f"nonce-{i:012d}" for i in range(50)]
    assert all(store.use(ADDRESS, nonce, now) for nonce in nonces)
    assert not any(store.use(ADDRESS, nonce, now) for nonce in nonces)
    assert len(store) == 50


def test_concurrent_uses_of_one_nonce_let_exactly_one_through(tmp_path: Path) -> None:
    """Two copies of a request racing on two threads: the lock makes the check-and-record one."""
    store = NonceStore(tmp_path / "nonces.log", window_s=300)
    now = int(time.time())
    start = threading.Barrier(8)

    def use() -> bool:
        start.wait()
        return store.use(ADDRESS, "raced-nonce-0001", now)

    with ThreadPoolExecutor(8) as pool:
        outcomes = list(pool.map(lambda _: use(), range(8)))
    assert outcomes.count(True) == 1


def test_a_nonce_is_forgotten_only_once_its_timestamp_is_out_of_the_window(
    tmp_path: Path,
) -> None:
    """Forgetting is harmless then: the request's timestamp alone gets a replay refused."""
    store = NonceStore(tmp_path / "nonces.log", window_s=300)
    now = int(time.time())
    assert store.use(ADDRESS, "inside-window-001", now - 299)
    assert not store.use(ADDRESS, "inside-window-001", now - 299)
    assert store.use(ADDRESS, "long-expired-0001", now - 302)
    assert store.use(ADDRESS, "long-expired-0001", now - 302)


def test_restart_loads_only_live_entries(tmp_path: Path) -> None:
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=300)
    now = int(time.time())
    assert store.use(ADDRESS, "live-nonce-000001", now)
    assert store.use(ADDRESS, "dead-nonce-000001", now - 400)
    store.close()
    reopened = NonceStore(path, window_s=300)
    assert len(reopened) == 1
    assert not reopened.use(ADDRESS, "live-nonce-000001", now)


def test_compaction_keeps_what_is_live_across_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=300, compact_after=10)
    now = int(time.time())
    for i in range(9):
        assert store.use(ADDRESS, f"expired-{i:08d}", now - 400)
    assert store.use(ADDRESS, "kept-nonce-000001", now)
    assert path.read_text().splitlines() == [f"{ADDRESS.lower()} kept-nonce-000001 {now + 301}"]
    store.close()
    assert not NonceStore(path, window_s=300).use(ADDRESS, "kept-nonce-000001", now)


def test_a_full_store_refuses_a_new_nonce_and_records_nothing(tmp_path: Path) -> None:
    """Forgetting a live nonce to make room would let its request be replayed: refuse instead,
    saying when the oldest one expires."""
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=300, max_entries=2)
    now = int(time.time())
    assert store.use(ADDRESS, "oldest-nonce-0001", now - 100)
    assert store.use(ADDRESS, "newest-nonce-0001", now)
    journal = path.read_text()
    with pytest.raises(NonceStoreFull) as full:
        store.use(ADDRESS, "refused-nonce-001", now)
    assert full.value.limit == 2
    assert 100 < full.value.retry_after_s <= 201, "the oldest expires at now - 100 + 301"
    assert len(store) == 2
    assert path.read_text() == journal
    assert not store.use(ADDRESS, "oldest-nonce-0001", now - 100), "a replay is still refused"
    store.close()
    with pytest.raises(NonceStoreFull):
        NonceStore(path, window_s=300, max_entries=2).use(ADDRESS, "refused-nonce-001", now)


def test_expired_nonces_make_room_in_a_full_store(tmp_path: Path) -> None:
    store = NonceStore(tmp_path / "nonces.log", window_s=300, max_entries=1)
    now = int(time.time())
    assert store.use(ADDRESS, "expired-nonce-001", now - 400)
    assert store.use(ADDRESS, "live-nonce-000001", now)
    with pytest.raises(NonceStoreFull):
        store.use(ADDRESS, "live-nonce-000002", now)


def test_an_address_past_its_share_is_refused_until_its_oldest_nonce_expires(
    tmp_path: Path,
) -> None:
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=1, max_entries=10, max_per_address=2)
    now = int(time.time())
    assert store.use(ADDRESS, "a" * 16, now - 2)
    assert store.use(ADDRESS, "b" * 16, now + 60)
    assert store.use(ADDRESS, "c" * 16, now)
    with pytest.raises(NonceQuotaExceeded) as refused:
        store.use(ADDRESS.lower(), "d" * 16, now)
    assert (refused.value.address, refused.value.limit) == (ADDRESS.lower(), 2)
    assert 0 < refused.value.retry_after_s <= 2
    assert not store.use(ADDRESS, "c" * 16, now)
    assert store.use("0x" + "1" * 40, "d" * 16, now)
    store.close()
    reopened = NonceStore(path, window_s=1, max_entries=10, max_per_address=2)
    with pytest.raises(NonceQuotaExceeded):
        reopened.use(ADDRESS, "e" * 16, now)
    assert len(reopened) == 3


def test_a_compaction_the_disk_refuses_fails_no_request(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The rewrite raised out of ``use``: the request whose nonce was already durable
    failed, and so did every signed request after it, each one trying again."""
    path = tmp_path / "nonces.log"
    store = NonceStore(path, window_s=1, compact_after=4)

    def refused(target: Path, data: bytes, *, mode: int = 0o644) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(durable, "atomic_write", refused)
    old = int(time.time()) - 10
    assert [store.use(ADDRESS, f"old-nonce-{i:06d}", old) for i in range(4)] == [True] * 4
    now = int(time.time())
    assert [store.use(ADDRESS, f"fresh-nonce-{i:04d}", now) for i in range(3)] == [True] * 3
    assert path.read_text().count("\n") == 7
    monkeypatch.undo()
    store.close()
    reopened = NonceStore(path, window_s=1)
    assert not reopened.use(ADDRESS, "fresh-nonce-0002", now)
