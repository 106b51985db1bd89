"""What a kill -9 left half-written is removed at the next start.

``atomic_write`` writes ``.<name>.<pid>.tmp`` and renames it into place; killed in between,
it left the temporary behind, and nothing ever removed it: the store only dropped packs that
never committed.
"""

from __future__ import annotations

from pathlib import Path

from services.cas.store import ContentStore
from tests.unit.services.cas.test_reachability import ALICE, put, raw

BLOCK = raw(b"a block stored before the kill")


def test_a_start_removes_the_temporaries_a_kill_left(tmp_path: Path) -> None:
    store = ContentStore.open(tmp_path, [])
    put(store, BLOCK)
    store.pins.add_all({BLOCK.cid: len(BLOCK.data)}, ALICE)
    store.close()
    kept = sorted(tmp_path.rglob("*"))
    leftovers = [
        tmp_path / "packs" / ".00000000000000000001-abcdef01.idx.4242.tmp",
        tmp_path / "quarantine" / f".{BLOCK.cid.multihash.hex()}.1700000000.4242.tmp",
        tmp_path / ".pins.log.4242.tmp",
    ]
    for leftover in leftovers:
        leftover.write_bytes(b"half written")
    reopened = ContentStore.open(tmp_path, [])
    try:
        assert sorted(tmp_path.rglob("*")) == kept
        assert reopened.blocks.get(BLOCK.cid) == BLOCK.data
        assert reopened.pinned() == {BLOCK.cid: frozenset({ALICE})}
    finally:
        reopened.close()
