"""Waiting for a service to reach a state, with a generous bound and no timed assertion."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def wait_for(check: Callable[[], Any], what: str, timeout_s: float = 120.0) -> Any:
    """Poll ``check`` until it returns something true; fail naming ``what`` past ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")
