"""Crash a writer with SIGKILL after it has acknowledged some writes, for durability tests;
make its disk fail its fsyncs."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.procs import REPO

FAILING_FSYNC = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static int failing(int fd) {
    const char *trigger = getenv("FAIL_FSYNC_WHILE");
    char link[64], path[4096];
    snprintf(link, sizeof link, "/proc/self/fd/%d", fd);
    ssize_t length = readlink(link, path, sizeof path - 1);
    if (trigger == NULL || length < 4) return 0;
    path[length] = 0;
    if (strcmp(path + length - 4, "-wal") != 0 || access(trigger, F_OK) != 0) return 0;
    if (getenv("FAIL_FSYNC_ONCE") != NULL) unlink(trigger);
    return 1;
}

int fsync(int fd) {
    if (failing(fd)) { errno = EIO; return -1; }
    return ((int (*)(int))dlsym(RTLD_NEXT, "fsync"))(fd);
}

int fdatasync(int fd) {
    if (failing(fd)) { errno = EIO; return -1; }
    return ((int (*)(int))dlsym(RTLD_NEXT, "fdatasync"))(fd);
}
"""


def failing_fsync_library(directory: Path) -> Path:
    """Build an ``LD_PRELOAD`` library in ``directory`` whose ``fsync`` and ``fdatasync`` of a
    write-ahead log (a file whose name ends in ``-wal``) fail with EIO while the file that
    ``$FAIL_FSYNC_WHILE`` names exists (with ``$FAIL_FSYNC_ONCE`` set, the failure removes
    it): a real failing disk under SQLite, not a mock."""
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc is needed to build the library that fails fsync")
    source = directory / "failing_fsync.c"
    source.write_text(FAILING_FSYNC)
    library = directory / "failing_fsync.so"
    subprocess.run([gcc, "-shared", "-fPIC", "-o", library, source, "-ldl"], check=True)
    return library


class FailingDiskChild:
    """``script`` run on ``path`` in a child process whose fsyncs of a write-ahead log fail
    while ``trigger`` exists (once, and the trigger is removed, unless ``persistent``), under
    ``library`` (``failing_fsync_library``). The script prints one line when it is ready and
    answers each line written to it with one line."""

    def __init__(
        self, script: str, path: Path, library: Path, trigger: Path, persistent: bool
    ) -> None:
        environment = {"PYTHONPATH": f"{REPO}:{REPO / 'clients'}", "LD_PRELOAD": str(library)}
        if not persistent:
            environment["FAIL_FSYNC_ONCE"] = "1"
        self.process = subprocess.Popen(
            [sys.executable, "-c", script, str(path)],
            cwd=REPO,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=environment | {"FAIL_FSYNC_WHILE": str(trigger)},
        )
        assert self.answer() == "ready"

    def answer(self) -> str:
        assert self.process.stdout is not None
        return self.process.stdout.readline().strip()

    def ask(self, line: str) -> str:
        assert self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()
        return self.answer()

    def kill(self) -> None:
        """SIGKILL the child; leaving the block closes its pipes and waits for it."""
        with self.process:
            self.process.send_signal(signal.SIGKILL)


def copy_as_killed(path: Path, directory: Path) -> Path:
    """Copy the SQLite database ``path`` and its write-ahead log into ``directory`` as a
    kill -9 of its writer would now leave them (the shared-memory index is rebuilt from the
    log by the first open, as after a kill); the copy's path."""
    directory.mkdir()
    for name in (path.name, f"{path.name}-wal"):
        shutil.copyfile(path.with_name(name), directory / name)
    return directory / path.name


def acknowledged_before_kill(script: str, path: Path, count: int) -> list[str]:
    """Run ``script`` on ``path`` in a new interpreter, read ``count`` lines, then kill -9 it.

    Each line the script prints is a write it has acknowledged; what the caller reopens after
    the kill must contain all of them.
    """
    with subprocess.Popen(
        [sys.executable, "-c", script, str(path)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        env={"PYTHONPATH": f"{REPO}:{REPO / 'clients'}"},
    ) as writer:
        assert writer.stdout is not None
        lines = [writer.stdout.readline().strip() for _ in range(count)]
        writer.send_signal(signal.SIGKILL)
    return lines


def output_of_killed(script: str, path: Path, *args: str) -> str:
    """Run ``script`` on ``path`` (and ``args``) in a new interpreter until it kills itself
    with SIGKILL at the point it chose; what it printed before."""
    child = subprocess.run(
        [sys.executable, "-c", script, str(path), *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={"PYTHONPATH": f"{REPO}:{REPO / 'clients'}"},
        timeout=120,
    )
    assert child.returncode == -signal.SIGKILL, child.stderr
    return child.stdout
