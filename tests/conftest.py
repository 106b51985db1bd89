"""Fixtures shared by every test layer."""

from __future__ import annotations

import gc
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from robocloud.identity import Identity
from tests.procs import ServiceProcess

ServiceFactory = Callable[..., ServiceProcess]


class LeftOpen(UserWarning):
    """Sockets or files a module's tests never closed (Python hides ``ResourceWarning``)."""


@pytest.fixture(autouse=True, scope="module")
def resources_left_open() -> Iterator[None]:
    """Name the module whose tests left a socket or file open. A client caught in a reference
    cycle is finalised by whichever later test the garbage collector runs in, and its
    ``ResourceWarning`` blamed that test: five CI logs named ``test_gas.py``, which allocates
    enough to start a collection, for sockets other modules had opened."""
    yield
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ResourceWarning)
        gc.collect()
    left_open = [str(w.message) for w in caught if issubclass(w.category, ResourceWarning)]
    if left_open:
        warnings.warn(LeftOpen(f"this module's tests left open: {left_open}"), stacklevel=1)


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
