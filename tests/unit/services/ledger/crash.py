"""Crash a writer with SIGKILL after it has acknowledged some writes, for durability tests."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from tests.procs import REPO


def acknowledged_before_kill(script: str, path: Path, count: int) -> list[str]:
    """Run ``script`` on ``path`` in a new interpreter, read ``count`` lines, then kill -9 it.

    Each line the script prints is a write it has acknowledged; what the caller reopens after
    the kill must contain all of them.
    """
    writer = subprocess.Popen(
        [sys.executable, "-c", script, str(path)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        env={"PYTHONPATH": f"{REPO}:{REPO / 'clients'}"},
    )
    assert writer.stdout is not None
    lines = [writer.stdout.readline().strip() for _ in range(count)]
    writer.send_signal(signal.SIGKILL)
    writer.wait()
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
