"""Real service processes for integration tests: free loopback ports, always stopped."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def audience_of(url: str) -> str:
    """The audience the service at ``url`` serves, which a V2 signature for it must name."""
    return str(httpx.get(f"{url}/v1/audience", timeout=10).json()["audience"])


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class ServiceProcess:
    """``python -m services.<name>`` on a free port with its own data directory."""

    def __init__(
        self, name: str, data_dir: Path, env: dict[str, str] | None = None, port: int | None = None
    ) -> None:
        self.name = name
        self.data_dir = data_dir
        self.port = port or free_port()
        self.env = {
            **os.environ,
            "ROBOCLOUD_HOST": "127.0.0.1",
            "ROBOCLOUD_PORT": str(self.port),
            "ROBOCLOUD_DATA_DIR": str(data_dir),
            "ROBOCLOUD_AUTH": "signed",
            "PYTHONUNBUFFERED": "1",
            **(env or {}),
        }
        self.process: subprocess.Popen[bytes] | None = None
        self.log_path = data_dir.parent / f"{name}-{self.port}.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def audience(self) -> str:
        return audience_of(self.url)

    def start(self, timeout_s: float = 30.0, *, ready: bool = True) -> ServiceProcess:
        """Start and wait until ``/readyz`` answers 200 (``/healthz`` when not ``ready``)."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("ab") as log:  # the child keeps its own descriptor
            self.process = subprocess.Popen(
                [sys.executable, "-m", f"services.{self.name}"],
                env=self.env,
                cwd=REPO,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        return self.wait("/readyz" if ready else "/healthz", timeout_s)

    def wait(self, probe: str = "/readyz", timeout_s: float = 30.0) -> ServiceProcess:
        """Poll ``probe`` until it answers 200; stop the process if it never does."""
        assert self.process is not None, "start() first"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"{self.name} exited at start:\n{self.log()}")
            try:
                if httpx.get(f"{self.url}{probe}", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"{self.name} not ready after {timeout_s} s:\n{self.log()}")

    def stop(self, *, kill: bool = False) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        if kill:
            self.process.kill()
        else:
            self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def restart(self) -> ServiceProcess:
        self.stop()
        return self.start()

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def logged(
        self, match: Callable[[dict[str, Any]], bool], count: int = 1, timeout_s: float = 10.0
    ) -> list[dict[str, Any]]:
        """The service's JSON log lines that ``match``, once there are ``count`` of them (or
        ``timeout_s`` has passed): a request's access line is written after its answer has
        gone, so a test holding the answer can be ahead of it."""
        deadline = time.monotonic() + timeout_s
        while True:
            found = [line for line in self._json_lines() if match(line)]
            if len(found) >= count or time.monotonic() > deadline:
                return found
            time.sleep(0.05)

    def _json_lines(self) -> list[dict[str, Any]]:
        lines = []
        for text in self.log().splitlines():
            with contextlib.suppress(ValueError):
                lines.append(json.loads(text))
        return [line for line in lines if isinstance(line, dict)]

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()
