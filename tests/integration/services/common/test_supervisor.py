"""`make up`'s supervisor: all five up and ready, clean stop, loud failure."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from tests.procs import REPO


def start_supervisor(data_dir: Path, **env: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.common.supervisor",
            "--free-ports",
            "--data-dir",
            str(data_dir),
        ],
        cwd=REPO,
        env={**os.environ, "ROBOCLOUD_AUTH": "signed", **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


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


def test_a_service_that_dies_at_start_fails_the_whole_start(tmp_path: Path) -> None:
    supervisor = start_supervisor(tmp_path, ROBOCLOUD_AUTH="not-a-mode")
    output = supervisor.communicate(timeout=60)[0]
    assert supervisor.returncode == 1
    assert "start-up failed" in output
    assert "exited with status" in output
