"""A real cas process per test, a robot's SDK client, and raw signed requests for bad input."""

from __future__ import annotations

import json
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import quote_plus

import httpx
import pytest

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.client import ServiceClient
from robocloud.errors import ApiError
from robocloud.identity import Identity
from tests.conftest import ServiceFactory
from tests.procs import ServiceProcess

QUIET_GC = {"ROBOCLOUD_CAS_GC_INTERVAL_S": "0"}


@pytest.fixture
def cas_service(service_factory: ServiceFactory) -> ServiceProcess:
    """A fresh cas for this test alone: for tests that look at the store as a whole."""
    return service_factory("cas", QUIET_GC)


@pytest.fixture(scope="module")
def shared_cas_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One cas for a whole test module; a module opts in by overriding ``cas_service``.

    Tests on a shared store check changes (``store_unchanged``), never absolute contents.
    """
    process = ServiceProcess("cas", tmp_path_factory.mktemp("shared-cas") / "cas", QUIET_GC)
    process.start()
    try:
        yield process
    finally:
        process.stop()


@contextmanager
def store_unchanged(service: ServiceProcess) -> Iterator[None]:
    """Assert that what runs inside stores no block and changes no pin."""
    before = (repo_stat(service.url)["NumObjects"], pin_list(service.url))
    yield
    assert (repo_stat(service.url)["NumObjects"], pin_list(service.url)) == before


def pin_list(url: str) -> Any:
    return httpx.post(f"{url}/api/v0/pin/ls").json()


@pytest.fixture
def cas(cas_service: ServiceProcess, identity: Identity) -> Iterator[Cas]:
    with Cas(cas_service.url, identity, retries=0) as client:
        yield client


@pytest.fixture
def signed(cas_service: ServiceProcess, identity: Identity) -> Iterator[ServiceClient]:
    """Signed raw requests, for bodies the SDK would never send."""
    with ServiceClient(cas_service.url, identity, retries=0) as client:
        yield client


def multipart(*files: tuple[str, bytes], boundary: str | None = None) -> tuple[bytes, str]:
    """A kubo-style multipart body and its Content-Type."""
    boundary = boundary or secrets.token_hex(8)
    body = b""
    for name, data in files:
        body += (
            f"--{boundary}\r\n"
            f'Content-Disposition: form-data; name="file"; filename="{name}"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        ).encode()
        body += data + b"\r\n"
    body += f"--{boundary}--\r\n".encode()
    return body, f"multipart/form-data; boundary={boundary}"


def post_files(signed: ServiceClient, path: str, *files: tuple[str, bytes]) -> httpx.Response:
    """A signed kubo RPC call with ``files`` as its multipart body."""
    body, content_type = multipart(*files)
    return signed.request("POST", path, content=body, headers={"Content-Type": content_type})


def tree_multipart(root: Path, name: str | None = None) -> tuple[bytes, str]:
    """A directory as ``ipfs add -r`` sends it: each directory part before its entries.

    Names are escaped with Go's ``url.QueryEscape``, as kubo's clients do.
    """
    boundary = secrets.token_hex(8)
    body = bytearray()
    top = name or root.name

    def part(path: str, content_type: str, data: bytes) -> None:
        body.extend(
            (
                f"--{boundary}\r\n"
                f'Content-Disposition: form-data; name="file"; filename="{quote_plus(path)}"\r\n'
                f"Content-Type: {content_type}\r\n\r\n"
            ).encode()
        )
        body.extend(data + b"\r\n")

    def walk(directory: Path, path: str) -> None:
        part(path, "application/x-directory", b"")
        for entry in sorted(directory.iterdir(), key=lambda entry: entry.name.encode()):
            if entry.is_dir():
                walk(entry, f"{path}/{entry.name}")
            else:
                part(f"{path}/{entry.name}", "application/octet-stream", entry.read_bytes())

    walk(root, top)
    body.extend(f"--{boundary}--\r\n".encode())
    return bytes(body), f"multipart/form-data; boundary={boundary}"


def repo_stat(url: str) -> dict[str, Any]:
    answer = httpx.post(f"{url}/api/v0/repo/stat").json()
    assert isinstance(answer, dict)
    return answer


def error_of(exc: pytest.ExceptionInfo[ApiError], status: int, code: str) -> ApiError:
    assert exc.value.status == status, exc.value
    assert exc.value.code == code, exc.value
    return exc.value


def corrupt_block(data_dir: Path, cid: CID) -> None:
    """Flip one byte of a stored block in its pack file, as disk rot would."""
    for index in (data_dir / "packs").glob("*.idx"):
        for key, offset, _ in json.loads(index.read_bytes()):
            if key == cid.multihash.hex():
                with index.with_suffix(".pack").open("r+b") as pack:
                    pack.seek(offset)
                    byte = pack.read(1)
                    pack.seek(offset)
                    pack.write(bytes([byte[0] ^ 0xFF]))
                return
    raise KeyError(str(cid))
