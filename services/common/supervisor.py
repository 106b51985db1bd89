"""``make up``: run the five services as local processes, like a tiny process supervisor.

Every child's log lines are prefixed with its service name; the supervisor waits until every
service answers ``/readyz``, prints the URLs, and on Ctrl-C or SIGTERM stops them all
(SIGTERM, then SIGKILL after a grace period). A service that dies during start-up stops the
whole system with a non-zero exit, so a broken build never looks half-up.

A service that dies later (killed for memory, a crash) is started again on its port and data
directory, after a delay that doubles with each death in a row, as Compose's ``restart:
unless-stopped`` does for the containers: the others keep serving and only its own requests
fail meanwhile. A service that keeps dying soon after each start is not going to mend by
itself; after ``max_restarts`` such deaths in a row the supervisor stops everything, loudly.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from types import FrameType

import httpx

from robocloud.config import SERVICES
from services.common.lifetime import die_with_parent

COLOURS = ("36", "33", "32", "35", "34")
STARTUP_ORDER = ("ledger", "cas", "storage", "broker", "fl")
FIRST_RESTART_DELAY_S = 1.0
LONGEST_RESTART_DELAY_S = 30.0
STABLE_AFTER_S = 60.0
"""A service that ran this long before it died starts its count of deaths in a row afresh."""


@dataclass
class Child:
    name: str
    port: int
    process: subprocess.Popen[bytes]
    started_at: float = field(default_factory=time.monotonic)
    deaths_in_a_row: int = 0
    restart_at: float | None = None
    """When the child, dead, is due to start again; None while it runs."""
    ready: bool = False

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def restart_delay(deaths_in_a_row: int) -> float:
    """1 s after a first death, doubling with each one in a row, 30 s at most."""
    return min(FIRST_RESTART_DELAY_S * 2.0 ** (deaths_in_a_row - 1), LONGEST_RESTART_DELAY_S)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _pump(name: str, process: subprocess.Popen[bytes], colour: str) -> None:
    """Copy a child's output line by line, prefixed with its name."""
    assert process.stdout is not None
    prefix = f"\x1b[{colour}m{name:<8}|\x1b[0m " if sys.stdout.isatty() else f"{name:<8}| "
    for raw in process.stdout:
        sys.stdout.write(prefix + raw.decode(errors="replace"))
        sys.stdout.flush()


class Supervisor:
    def __init__(
        self,
        ports: dict[str, int],
        data_dir: Path,
        host: str = "127.0.0.1",
        max_restarts: int = 5,
    ) -> None:
        self.ports = ports
        self.data_dir = data_dir
        self.host = host
        self.max_restarts = max_restarts
        self.children: list[Child] = []
        self._stopping = threading.Event()

    def environment(self, name: str) -> dict[str, str]:
        env = dict(os.environ)
        env.update(
            {
                "ROBOCLOUD_HOST": self.host,
                "ROBOCLOUD_PORT": str(self.ports[name]),
                "ROBOCLOUD_DATA_DIR": str(self.data_dir / name),
                "PYTHONUNBUFFERED": "1",
            }
        )
        for peer, port in self.ports.items():
            env[f"ROBOCLOUD_{peer.upper()}_URL"] = f"http://127.0.0.1:{port}"
        return env

    def spawn(self, name: str) -> subprocess.Popen[bytes]:
        """Start service ``name`` with its output copied to ours. Called on the main thread
        only: the kernel signals a child when the thread that forked it ends."""
        process = subprocess.Popen(
            [sys.executable, "-m", f"services.{name}"],
            env=self.environment(name),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=partial(die_with_parent, signal.SIGTERM),
        )
        colour = COLOURS[STARTUP_ORDER.index(name) % len(COLOURS)]
        threading.Thread(target=_pump, args=(name, process, colour), daemon=True).start()
        return process

    def start(self) -> None:
        for name in STARTUP_ORDER:
            self.children.append(Child(name, self.ports[name], self.spawn(name)))

    def wait_ready(self, timeout_s: float) -> None:
        """Return once every service is ready; raise if one exits or the time runs out."""
        deadline = time.monotonic() + timeout_s
        pending = {child.name: child for child in self.children}
        with httpx.Client(timeout=1.0) as http:
            while pending:
                for name, child in list(pending.items()):
                    code = child.process.poll()
                    if code is not None:
                        raise RuntimeError(f"{name} exited with status {code} during start-up")
                    if is_ready(http, child):
                        child.ready = True
                        del pending[name]
                if time.monotonic() > deadline:
                    raise RuntimeError(f"not ready after {timeout_s:.0f} s: {', '.join(pending)}")
                time.sleep(0.2)

    def watch(self) -> int:
        """Block until a signal asks to stop (0) or a service dies too often in a row (1),
        starting again those that die meanwhile."""
        with httpx.Client(timeout=1.0) as http:
            while not self._stopping.wait(0.5):
                for child in self.children:
                    if not self.tend(child, http):
                        print("supervisor| stopping all")
                        return 1
        return 0

    def tend(self, child: Child, http: httpx.Client) -> bool:
        """One look at ``child``: note its death and when to start it again, start it when
        due, report it ready again. False once it has died ``max_restarts`` times in a row."""
        now = time.monotonic()
        if child.restart_at is not None:
            if now >= child.restart_at:
                print(f"supervisor| starting {child.name} again")
                child.process = self.spawn(child.name)
                child.started_at, child.restart_at, child.ready = now, None, False
            return True
        code = child.process.poll()
        if code is None:
            if not child.ready and is_ready(http, child):
                child.ready = True
                print(f"supervisor| {child.name} ready again at {child.url}")
            return True
        ran_for = now - child.started_at
        child.deaths_in_a_row = 1 if ran_for >= STABLE_AFTER_S else child.deaths_in_a_row + 1
        if child.deaths_in_a_row > self.max_restarts:
            print(
                f"supervisor| {child.name} exited with status {code} after {ran_for:.0f} s,"
                f" its death {child.deaths_in_a_row} in a row; giving up"
            )
            return False
        delay = restart_delay(child.deaths_in_a_row)
        print(
            f"supervisor| {child.name} exited with status {code} after {ran_for:.0f} s;"
            f" starting it again in {delay:.0f} s"
            f" (restart {child.deaths_in_a_row} of {self.max_restarts} in a row)"
        )
        child.restart_at = now + delay
        return True

    def request_stop(self, signum: int, _frame: FrameType | None) -> None:
        print(f"supervisor| {signal.Signals(signum).name}: stopping services")
        self._stopping.set()

    def stop(self, grace_s: float = 10.0) -> None:
        for child in self.children:
            if child.process.poll() is None:
                child.process.terminate()
        deadline = time.monotonic() + grace_s
        for child in self.children:
            try:
                child.process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.process.kill()
                child.process.wait()


def is_ready(http: httpx.Client, child: Child) -> bool:
    try:
        return http.get(f"{child.url}/readyz").status_code == 200
    except httpx.HTTPError:
        return False


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--data-dir", type=Path, default=Path("data"))
    parser.add_argument("--free-ports", action="store_true", help="pick free ports (tests)")
    parser.add_argument("--timeout", type=float, default=30.0, help="start-up limit, seconds")
    parser.add_argument(
        "--max-restarts",
        type=int,
        default=5,
        help="deaths in a row of one service (each within a minute of its start) to restart"
        " it after; one more stops everything",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    ports = {name: free_port() if args.free_ports else port for name, port in SERVICES.items()}
    supervisor = Supervisor(ports, args.data_dir, max_restarts=args.max_restarts)
    signal.signal(signal.SIGINT, supervisor.request_stop)
    signal.signal(signal.SIGTERM, supervisor.request_stop)
    supervisor.start()
    try:
        supervisor.wait_ready(args.timeout)
    except RuntimeError as exc:
        print(f"supervisor| start-up failed: {exc}")
        supervisor.stop()
        return 1
    print("supervisor| all services ready:")
    for child in supervisor.children:
        print(f"supervisor|   {child.name:<8} {child.url}   docs: {child.url}/docs")
    print("supervisor| Ctrl-C stops everything")
    code = supervisor.watch()
    supervisor.stop()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
