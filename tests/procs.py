"""Real service processes for integration tests: free loopback ports, always stopped."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import random
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


PORTS = range(10_000, 32_768)
"""Where test services listen: below Linux's ephemeral range (32768-60999), out of which the
kernel picks the port of every outgoing connection and of every ``bind`` to port 0."""


def _worker_ports() -> range:
    """This pytest-xdist worker's share of ``PORTS`` (all of them outside xdist): a port
    the kernel handed out by ``bind`` to port 0 and released again could be handed to
    another worker before the service meant for it bound it, or while it restarted, and
    the test then talked to the other worker's service."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    share = len(PORTS) // max(workers, 1)
    first = PORTS.start + (worker % max(workers, 1)) * share
    return range(first, first + share)


_SHARE = _worker_ports()
_IN_TURN = itertools.islice(itertools.cycle(_SHARE), random.randrange(len(_SHARE)), None)
"""From a random place in the share: two pytest sessions on one machine (two checkouts, or a
run beside CI) both started at its first port and took the same ports in the same order, and
a test talked to the other session's service."""


def free_port() -> int:
    """A loopback port nobody listens on, from this worker's share, each in turn: a port is
    handed out again only after every other one of the share, long after its test ended."""
    for _ in range(len(_SHARE)):
        port = next(_IN_TURN)
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port in {_SHARE}")


NO_PEERS = {
    f"ROBOCLOUD_{service.upper()}_URL": "http://127.0.0.1:9"
    for service in ("cas", "ledger", "storage", "broker", "fl")
}
"""The other services a test's service reaches unless the test names them: a closed port
(discard, which no test can bind). They were the defaults, 127.0.0.1:8080 to 8084, where a
`make up` beside the tests answered: one run of the ledger and storage tests sent it 1,000
JSON-RPC and registry calls and 29 cas uploads, and granted its storage node a role on each
test's chain, transactions the tests never sent."""


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
            **NO_PEERS,
            "ROBOCLOUD_HOST": "127.0.0.1",
            "ROBOCLOUD_PORT": str(self.port),
            "ROBOCLOUD_DATA_DIR": str(data_dir),
            "ROBOCLOUD_AUTH": "signed",
            "PYTHONUNBUFFERED": "1",
            **(env or {}),
        }
        if name == "ledger" and not {"ROBOCLOUD_STORAGE_URL", "ROBOCLOUD_LEDGER_GRANT_ROLES"} & set(
            env or {}
        ):
            # It grants the storage role to the node a test names, else to none.
            self.env["ROBOCLOUD_LEDGER_GRANT_ROLES"] = ""
        self.process: subprocess.Popen[bytes] | None = None
        self.log_path = data_dir.parent / f"{name}-{self.port}.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def audience(self) -> str:
        return audience_of(self.url)

    def start(self, timeout_s: float = 30.0, *, ready: bool = True) -> ServiceProcess:
        """Start and wait until ``/readyz`` answers 200 (``/healthz`` when not ``ready``).

        Refused while its process runs: ``with ServiceProcess(...).start()`` started a second
        one on entering, and the first ran on after the ``with``, orphaned."""
        if self.process is not None and self.process.poll() is None:
            raise RuntimeError(f"{self.name} on port {self.port} is running already")
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
                    return self._checked_to_be_ours()
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"{self.name} not ready after {timeout_s} s:\n{self.log()}")

    def _checked_to_be_ours(self) -> ServiceProcess:
        """Ready, and the service on the port is this process's: another one that took the
        port first answered the probe while this one failed to bind."""
        answering = httpx.get(f"{self.url}/healthz", timeout=5).json().get("service")
        assert self.process is not None
        if self.process.poll() is not None or answering != self.name:
            self.stop()
            raise RuntimeError(
                f"{self.name} on port {self.port}: {answering} answered there:\n{self.log()}"
            )
        return self

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


def memory_kib(process: ServiceProcess) -> dict[str, int]:
    """VmRSS (now) and VmHWM (the peak so far) of the service process, in KiB."""
    assert process.process is not None
    fields = {}
    with open(f"/proc/{process.process.pid}/status") as status:
        for line in status:
            name, _, value = line.partition(":")
            if name in ("VmRSS", "VmHWM"):
                fields[name] = int(value.split()[0])
    return fields
