"""``add``'s sink in process: what one upload stages, commits and pins."""

from __future__ import annotations

from pathlib import Path

from robocloud.unixfs import ImportParams
from services.cas.store import ContentStore
from services.cas.uploads import FileAdder

ROBOT = "0x" + "ab" * 20
FILES = 200


def add_files(adder: FileAdder, files: dict[str, bytes]) -> None:
    for name, data in files.items():
        adder.begin(name)
        adder.write(data)
        adder.end()


def journal_lines(path: Path) -> int:
    return path.read_bytes().count(b"\n") if path.exists() else 0


def test_an_add_pins_all_its_top_level_items_in_one_journal_line(
    store: ContentStore, tmp_path: Path
) -> None:
    """Each top-level item was pinned on its own line and fsync (2,000 files, 2,003 fsyncs),
    so a failure part way kept some pins; docs/cas.md promises one line a request."""
    files = {f"top-{i}.txt": f"file {i}".encode() for i in range(FILES)}
    files["d/inner.txt"] = b"inside d"
    adder = FileAdder(store, ImportParams(), only_hash=False, pin=True)
    add_files(adder, files)
    journal = tmp_path / "pins.log"
    before = journal_lines(journal)

    added = adder.commit(ROBOT)
    adder.discard()

    assert journal_lines(journal) == before + 1
    top_level = {item.cid for item in added if "/" not in item.name}
    assert len(top_level) == FILES + 1  # the files and the directory d
    assert set(store.pins.snapshot()) == top_level
    assert all(owners == {ROBOT} for owners in store.pins.snapshot().values())
