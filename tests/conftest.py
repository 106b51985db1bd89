"""Fixtures shared by every test layer."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from robocloud.identity import Identity
from tests.procs import ServiceProcess

ServiceFactory = Callable[..., ServiceProcess]


@pytest.fixture
def identity() -> Identity:
    return Identity.generate()


@pytest.fixture
def keystore(identity: Identity, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``identity`` in a keystore the CLI opens (its passphrase in the environment)."""
    path = tmp_path / "key.json"
    identity.save(path, "pw", scrypt_n=2**4)
    monkeypatch.setenv("ROBOCLOUD_PASSPHRASE", "pw")
    return path


@pytest.fixture
def service_factory(tmp_path: Path) -> Iterator[ServiceFactory]:
    """Start real service processes; every one is stopped when the test ends, even on failure."""
    started: list[ServiceProcess] = []

    def start(
        name: str,
        env: dict[str, str] | None = None,
        data_dir: Path | None = None,
        *,
        ready: bool = True,
        port: int | None = None,
    ) -> ServiceProcess:
        data_dir = data_dir or tmp_path / f"{name}-{len(started)}"
        process = ServiceProcess(name, data_dir, env, port=port)
        started.append(process)
        return process.start(ready=ready)

    yield start
    for process in started:
        process.stop()
