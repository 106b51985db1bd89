"""``make up``: run the five services as local processes, like a tiny process supervisor.

Every child's log lines are prefixed with its service name; the supervisor waits until every
service answers ``/readyz``, prints the URLs, and on Ctrl-C or SIGTERM stops them all
(SIGTERM, then SIGKILL after a grace period). A service that dies during start-up stops the
whole system with a non-zero exit, so a broken build never looks half-up.
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
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import FrameType

import httpx

from robocloud.config import SERVICES
from services.common.lifetime import die_with_parent

COLOURS = ("36", "33", "32", "35", "34")
STARTUP_ORDER = ("ledger", "cas", "storage", "broker", "fl")


@dataclass
class Child:
    name: str
    port: int
    process: subprocess.Popen[bytes]

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _pump(child: Child, colour: str) -> None:
    """Copy a child's output line by line, prefixed with its name."""
    assert child.process.stdout is not None
    prefix = (
        f"\x1b[{colour}m{child.name:<8}|\x1b[0m " if sys.stdout.isatty() else f"{child.name:<8}| "
    )
    for raw in child.process.stdout:
        sys.stdout.write(prefix + raw.decode(errors="replace"))
        sys.stdout.flush()


class Supervisor:
    def __init__(self, ports: dict[str, int], data_dir: Path, host: str = "127.0.0.1") -> None:
        self.ports = ports
        self.data_dir = data_dir
        self.host = host
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

    def start(self) -> None:
        for index, name in enumerate(STARTUP_ORDER):
            process = subprocess.Popen(
                [sys.executable, "-m", f"services.{name}"],
                env=self.environment(name),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=partial(die_with_parent, signal.SIGTERM),
            )
            child = Child(name, self.ports[name], process)
            self.children.append(child)
            colour = COLOURS[index % len(COLOURS)]
            threading.Thread(target=_pump, args=(child, colour), daemon=True).start()

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
                    try:
                        if http.get(f"{child.url}/readyz").status_code == 200:
                            del pending[name]
                    except httpx.HTTPError:
                        pass
                if time.monotonic() > deadline:
                    raise RuntimeError(f"not ready after {timeout_s:.0f} s: {', '.join(pending)}")
                time.sleep(0.2)

    def watch(self) -> int:
        """Block until a signal asks to stop (0) or a service dies (1)."""
        while not self._stopping.wait(0.5):
            for child in self.children:
                code = child.process.poll()
                if code is not None:
                    print(f"supervisor| {child.name} exited with status {code}; stopping all")
                    return 1
        return 0

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


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--data-dir", type=Path, default=Path("data"))
    parser.add_argument("--free-ports", action="store_true", help="pick free ports (tests)")
    parser.add_argument("--timeout", type=float, default=30.0, help="start-up limit, seconds")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    ports = {name: free_port() if args.free_ports else port for name, port in SERVICES.items()}
    supervisor = Supervisor(ports, args.data_dir)
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
