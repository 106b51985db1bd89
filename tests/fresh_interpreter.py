"""Code run in a fresh interpreter: what importing a module loads or changes shows only
there, as a test process has long imported everything."""

from __future__ import annotations

import subprocess
import sys


def printed_by(code: str, timeout_s: float = 120) -> str:
    """What ``code`` prints, run by this Python in a new process (which must succeed)."""
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=timeout_s
    )
    return done.stdout
