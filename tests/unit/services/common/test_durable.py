"""Durable files: a journal line is whole or absent, a generated secret is whole or absent."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.common import durable
from services.common.durable import AppendLog, generated_secret
from tests.procs import REPO


def test_a_torn_last_line_is_cut_at_open_so_the_next_line_stays_whole(tmp_path: Path) -> None:
    path = tmp_path / "journal.log"
    journal = AppendLog(path)
    journal.append("one")
    journal.close()
    with path.open("ab") as file:
        file.write(b"tw")
    journal = AppendLog(path)
    assert path.read_bytes() == b"one\n"
    journal.append("three")
    journal.close()
    assert AppendLog(path).read_lines() == ["one", "three"]


def test_a_short_write_is_finished_and_a_failed_one_leaves_the_file_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``os.write`` wrote part of a line and said so in its count; the journal acknowledged
    the line, and the next one was glued onto its half."""
    path = tmp_path / "journal.log"
    journal = AppendLog(path)
    journal.append("before")
    real_write = os.write
    calls: list[int] = []

    def short_then(fd: int, data: bytes | memoryview) -> int:
        calls.append(len(data))
        if len(calls) == 1:
            return real_write(fd, bytes(data[:3]))
        if fail_after_short:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", short_then)
    fail_after_short = False
    journal.append("finished")
    assert calls == [len(b"finished\n"), len(b"finished\n") - 3]
    calls.clear()
    fail_after_short = True
    with pytest.raises(OSError, match="No space left"):
        journal.append("refused")
    assert path.read_bytes() == b"before\nfinished\n"
    monkeypatch.undo()
    journal.append("after")
    journal.close()
    assert AppendLog(path).read_lines() == ["before", "finished", "after"]


def test_an_empty_secret_file_left_by_a_crash_is_generated_again(tmp_path: Path) -> None:
    path = tmp_path / "node.secret"
    path.touch(mode=0o600)
    secret = generated_secret(path)
    assert len(secret) >= 43
    assert path.read_text() == secret
    assert generated_secret(path) == secret
    assert sorted(p.name for p in tmp_path.iterdir()) == ["node.secret"]


def test_processes_starting_together_agree_on_one_secret(tmp_path: Path) -> None:
    path = tmp_path / "node.secret"
    script = (
        "import sys; from pathlib import Path; "
        "from services.common.durable import generated_secret; "
        "print(generated_secret(Path(sys.argv[1])))"
    )
    starts = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(path)],
            cwd=REPO,
            stdout=subprocess.PIPE,
            text=True,
            env={"PYTHONPATH": f"{REPO}:{REPO / 'clients'}"},
        )
        for _ in range(6)
    ]
    secrets = {start.communicate(timeout=60)[0].strip() for start in starts}
    assert secrets == {path.read_text()}
    assert oct(path.stat().st_mode & 0o777) == "0o600"


def test_a_compaction_failing_after_its_rename_leaves_appends_going_to_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Syncing the directory failed after the compacted file replaced the journal: the
    descriptor stayed on the replaced file, and every later line went where no name leads."""
    path = tmp_path / "journal.log"
    journal = AppendLog(path)
    for line in ("dead", "live"):
        journal.append(line)

    def failing(directory: Path) -> None:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(durable, "fsync_dir", failing)
    with pytest.raises(OSError, match="Input/output error"):
        journal.rewrite(["live"])
    monkeypatch.undo()
    journal.append("after")
    assert path.read_text() == "live\nafter\n"


def test_an_error_after_sqlite_rolled_back_by_itself_is_the_one_raised(tmp_path: Path) -> None:
    """SQLite rolls a transaction back itself on some I/O errors and a full disk; the ROLLBACK
    that followed was refused ("no transaction is active"), and that refusal was raised in
    place of the error that failed the write (the chain store, the event index and the
    anchorer's epochs all did so)."""
    db = durable.open_sqlite(tmp_path / "kv.sqlite", "CREATE TABLE kv (k TEXT)", synchronous="FULL")
    db.execute("INSERT INTO kv VALUES ('kept')")

    def write_rolled_back_by_sqlite() -> None:
        with durable.write_transaction(db):
            db.execute("INSERT INTO kv VALUES ('lost')")
            db.execute("ROLLBACK")
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        write_rolled_back_by_sqlite()
    with durable.write_transaction(db):
        db.execute("INSERT INTO kv VALUES ('later')")
    assert [row for (row,) in db.execute("SELECT k FROM kv")] == ["kept", "later"]
