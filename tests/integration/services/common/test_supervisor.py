"""`make up`'s supervisor: all five up and ready, clean stop, a dead service started again,
loud failure."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from tests.procs import REPO


def start_supervisor(data_dir: Path, *args: str, **env: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.common.supervisor",
            "--free-ports",
            "--data-dir",
            str(data_dir),
            *args,
        ],
        cwd=REPO,
        env={**os.environ, "ROBOCLOUD_AUTH": "signed", **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


class Output:
    """A supervisor's output, read on a thread of its own so a test can wait for a line while
    the supervisor goes on writing."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        assert process.stdout is not None
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self._stream = process.stdout
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self._stream:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()

    def wait_for(self, pattern: str, timeout_s: float = 60.0) -> re.Match[str]:
        """The first line, of those read or still to come, that matches ``pattern``."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._changed:
            while True:
                for line in self.lines[seen:]:
                    if match := re.search(pattern, line):
                        return match
                seen = len(self.lines)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"no line matched {pattern!r} in {timeout_s} s")
                self._changed.wait(left)

    def server_pids(self) -> dict[str, list[int]]:
        """Each service's uvicorn server processes, in the order they started."""
        pids: dict[str, list[int]] = {}
        with self._changed:
            for line in self.lines:
                if match := re.match(r"(\w+)\s*\|.*Started server process \[(\d+)\]", line):
                    pids.setdefault(match[1], []).append(int(match[2]))
        return pids

    def ready_urls(self) -> dict[str, str]:
        self.wait_for("Ctrl-C stops everything")
        with self._changed:
            return {
                match[1]: match[2]
                for line in self.lines
                if (match := re.match(r"supervisor\|\s+(\w+)\s+(http://\S+)\s", line))
            }


def robocloud(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-c", "from robocloud.cli import app; app()", *args]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=60)


def check_cli_against(urls: dict[str, str], tmp_path: Path) -> None:
    """The operator's first steps: make a key, see the platform, prove who they are."""
    env = {
        **os.environ,
        "COLUMNS": "200",
        "ROBOCLOUD_KEYSTORE": str(tmp_path / "robot.json"),
        "ROBOCLOUD_PASSPHRASE": "robot passphrase",
        **{f"ROBOCLOUD_{name.upper()}_URL": url for name, url in urls.items()},
    }
    created = robocloud(env, "keys", "new")
    assert created.returncode == 0, created.stderr
    address = re.search(r"address\s+(0x[0-9a-fA-F]{40})", created.stdout)
    assert address is not None
    assert address[1] in robocloud(env, "keys", "show").stdout
    again = robocloud(env, "keys", "new")
    assert again.returncode == 1
    assert "refusing to overwrite" in again.stderr
    status = robocloud(env, "status")
    assert status.returncode == 0, status.stdout
    assert status.stdout.count("│ ready") == 5
    whoami = robocloud(env, "whoami")
    assert whoami.returncode == 0, whoami.stdout + whoami.stderr
    assert whoami.stdout.count(address[1]) == 6
    wrong = robocloud({**env, "ROBOCLOUD_PASSPHRASE": "wrong"}, "whoami")
    assert wrong.returncode == 1
    assert "wrong passphrase" in wrong.stderr


def test_all_services_come_up_and_stop_on_sigterm(tmp_path: Path) -> None:
    supervisor = start_supervisor(tmp_path)
    assert supervisor.stdout is not None
    urls: dict[str, str] = {}
    try:
        deadline = time.monotonic() + 60
        for line in supervisor.stdout:
            match = re.match(r"supervisor\|\s+(\w+)\s+(http://\S+)", line)
            if match:
                urls[match[1]] = match[2]
            if "Ctrl-C" in line or time.monotonic() > deadline:
                break
        assert sorted(urls) == ["broker", "cas", "fl", "ledger", "storage"]
        for name, url in urls.items():
            assert httpx.get(f"{url}/healthz").json()["service"] == name
        check_cli_against(urls, tmp_path)
        supervisor.send_signal(signal.SIGTERM)
        rest = supervisor.communicate(timeout=30)[0]
    finally:
        supervisor.kill()
        supervisor.wait()
    assert supervisor.returncode == 0
    assert "SIGTERM: stopping services" in rest
    for url in urls.values():
        try:
            httpx.get(f"{url}/healthz", timeout=1)
        except httpx.ConnectError:
            continue
        raise AssertionError(f"{url} still answers after the supervisor stopped")


def test_services_do_not_outlive_a_killed_supervisor(tmp_path: Path) -> None:
    pids: list[int] = []
    with start_supervisor(tmp_path) as supervisor:
        assert supervisor.stdout is not None
        for line in supervisor.stdout:
            pids += [int(pid) for pid in re.findall(r"Started server process \[(\d+)\]", line)]
            if "Ctrl-C" in line:
                break
        supervisor.kill()
    assert len(pids) == 5
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and any(Path(f"/proc/{pid}").exists() for pid in pids):
        time.sleep(0.2)
    assert not any(Path(f"/proc/{pid}").exists() for pid in pids)


def first_block_hash(ledger_url: str) -> str:
    params = ["0x1", False]
    request = {"jsonrpc": "2.0", "id": 1, "method": "eth_getBlockByNumber", "params": params}
    block = httpx.post(f"{ledger_url}/rpc", json=request, timeout=10).json()["result"]
    return str(block["hash"])


def test_a_service_killed_later_is_started_again_alone_on_its_data(tmp_path: Path) -> None:
    with start_supervisor(tmp_path) as supervisor:
        output = Output(supervisor)
        try:
            urls = output.ready_urls()
            before = output.server_pids()
            chain = first_block_hash(urls["ledger"])
            os.kill(before["ledger"][0], signal.SIGKILL)
            output.wait_for(r"ledger exited with status -9 after \d+ s; starting it again in 1 s")
            output.wait_for(f"ledger ready again at {re.escape(urls['ledger'])}")
            after = output.server_pids()
            for name, url in urls.items():
                assert httpx.get(f"{url}/readyz").status_code == 200, name
            assert first_block_hash(urls["ledger"]) == chain
        finally:
            supervisor.terminate()
            supervisor.wait(30)
    assert len(after.pop("ledger")) == 2
    assert after == {name: pids for name, pids in before.items() if name != "ledger"}
    assert supervisor.returncode == 0


def test_a_service_that_keeps_dying_stops_everything(tmp_path: Path) -> None:
    with start_supervisor(tmp_path, "--max-restarts", "1") as supervisor:
        output = Output(supervisor)
        try:
            urls = output.ready_urls()
            shutil.rmtree(tmp_path / "cas")
            (tmp_path / "cas").write_text("a file where cas keeps its data")
            os.kill(output.server_pids()["cas"][0], signal.SIGKILL)
            output.wait_for(r"cas exited with status -9 after \d+ s; starting it again in 1 s")
            output.wait_for(r"starting cas again")
            output.wait_for(r"cas exited with status 1 after \d+ s, its death 2 in a row; giving")
            supervisor.wait(30)
        finally:
            supervisor.kill()
            supervisor.wait()
    assert supervisor.returncode == 1
    for url in urls.values():
        with pytest.raises(httpx.ConnectError):
            httpx.get(f"{url}/healthz", timeout=1)


def test_a_service_that_dies_at_start_fails_the_whole_start(tmp_path: Path) -> None:
    supervisor = start_supervisor(tmp_path, ROBOCLOUD_AUTH="not-a-mode")
    output = supervisor.communicate(timeout=60)[0]
    assert supervisor.returncode == 1
    assert "start-up failed" in output
    assert "exited with status" in output
