"""``Cas``: put and get content through a robocloud (or any kubo-compatible) gateway.

The robot trusts nothing but the CID. ``add`` computes the CID locally while it uploads and
refuses an answer that differs; ``get`` fetches a CAR and verifies every block against its
CID before reassembling the file, so a lying gateway can at worst withhold data.
"""

from __future__ import annotations

import hashlib
import json
import secrets
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from robocloud.car import CarError, CarReader
from robocloud.cid import CID
from robocloud.client import ServiceClient
from robocloud.config import service_url
from robocloud.errors import RobocloudError
from robocloud.identity import Identity
from robocloud.unixfs import Importer, ImportParams, UnixfsError, read_file

READ_SIZE = 1 << 20
CAR_MEDIA_TYPE = "application/vnd.ipld.car"
Progress = Callable[[int], None]


class CasError(RobocloudError):
    """The gateway's answer cannot be trusted: a CID mismatch, a bad or incomplete CAR."""


def _no_progress(_: int) -> None:
    return None


class _Multipart:
    """A one-file multipart/form-data body whose bytes (and so its digest) are fixed upfront."""

    def __init__(self, path: Path, name: str) -> None:
        self.path = path
        self.boundary = "robocloud-" + secrets.token_hex(16)
        safe_name = name.replace('"', "_").replace("\r", "_").replace("\n", "_")
        self.head = (
            f"--{self.boundary}\r\n"
            f'Content-Disposition: form-data; name="file"; filename="{safe_name}"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        ).encode()
        self.tail = f"\r\n--{self.boundary}--\r\n".encode()
        self.length = len(self.head) + path.stat().st_size + len(self.tail)

    @property
    def content_type(self) -> str:
        return f"multipart/form-data; boundary={self.boundary}"

    def sha256(self) -> str:
        """The body's digest, for the signature, read from the file without holding it."""
        digest = hashlib.sha256(self.head)
        buffer = bytearray(READ_SIZE)
        view = memoryview(buffer)
        with self.path.open("rb") as handle:
            while read := handle.readinto(buffer):
                digest.update(view[:read])
        digest.update(self.tail)
        return digest.hexdigest()

    def chunks(self, progress: Progress, on_content: Callable[[bytes], object]) -> Iterator[bytes]:
        yield self.head
        with self.path.open("rb") as handle:
            while chunk := handle.read(READ_SIZE):
                on_content(chunk)
                progress(len(chunk))
                yield chunk
        yield self.tail


class _IteratorReader:
    """A read-only binary stream over an iterator of byte chunks (a streamed HTTP body)."""

    def __init__(self, chunks: Iterator[bytes]) -> None:
        self._chunks = chunks
        self._buffer = bytearray()

    def read(self, size: int = -1) -> bytes:
        while size < 0 or len(self._buffer) < size:
            chunk = next(self._chunks, None)
            if chunk is None:
                break
            self._buffer += chunk
        if size < 0:
            size = len(self._buffer)
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data


class Cas:
    """The content-addressed store as a robot sees it."""

    def __init__(
        self, base_url: str | None = None, identity: Identity | None = None, **options: Any
    ) -> None:
        self.http = ServiceClient(base_url or service_url("cas"), identity, **options)

    def __enter__(self) -> Cas:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def add_bytes(
        self, data: bytes, *, pin: bool = True, params: ImportParams | None = None
    ) -> CID:
        with tempfile.NamedTemporaryFile() as handle:
            handle.write(data)
            handle.flush()
            return self.add_file(Path(handle.name), pin=pin, params=params, name="data")

    def add_file(
        self,
        path: Path,
        *,
        pin: bool = True,
        params: ImportParams | None = None,
        name: str | None = None,
        progress: Progress = _no_progress,
    ) -> CID:
        """Upload a file; return its CID once the gateway's answer matches the local one.

        The local CID is computed from the bytes as they are sent, so the robot hashes its
        file while the gateway works on the previous chunk.
        """
        params = params or ImportParams()
        body = _Multipart(path, name or path.name)
        importer = Importer(params)
        response = self.http.request(
            "POST",
            "/api/v0/add",
            params={
                "cid-version": params.cid_version,
                "raw-leaves": str(params.raw_leaves).lower(),
                "chunker": f"size-{params.chunk_size}",
                "pin": str(pin).lower(),
            },
            content=body.chunks(progress, importer.feed),
            content_sha256=body.sha256(),
            headers={"Content-Type": body.content_type, "Content-Length": str(body.length)},
        )
        _, expected, _ = importer.finish()
        answers = [line for line in response.text.splitlines() if line.strip()]
        try:
            reported = CID.decode(_json_line(answers[-1])["Hash"])
        except (IndexError, KeyError, ValueError) as exc:
            answer = response.text[:200]
            raise CasError(f"the gateway's add answer has no valid Hash: {answer!r}") from exc
        if reported != expected:
            raise CasError(f"the gateway says {reported}, but the file's CID is {expected}")
        return expected

    def get(self, cid: CID | str) -> bytes:
        """The verified content of a file."""
        with tempfile.TemporaryDirectory() as scratch:
            output = Path(scratch) / "content"
            self.get_to_file(cid, output)
            return output.read_bytes()

    def get_to_file(self, cid: CID | str, path: Path, progress: Progress = _no_progress) -> int:
        """Fetch a file as a CAR, verify every block, and write its content to ``path``."""
        root = CID.decode(cid) if isinstance(cid, str) else cid
        with tempfile.TemporaryDirectory(prefix="robocloud-car-") as scratch:
            blocks = Path(scratch)
            self._fetch_verified_car(root, blocks, progress)

            def get_block(wanted: CID) -> bytes:
                try:
                    return (blocks / str(wanted)).read_bytes()
                except FileNotFoundError as exc:
                    raise CasError(f"the gateway's CAR lacks block {wanted} of {root}") from exc

            partial = path.with_name(f".{path.name}.partial")
            written = 0
            try:
                with partial.open("wb") as out:
                    for piece in read_file(root, get_block):
                        out.write(piece)
                        written += len(piece)
            except (UnixfsError, CasError):
                partial.unlink(missing_ok=True)
                raise
            partial.replace(path)
            return written

    def _fetch_verified_car(self, root: CID, into: Path, progress: Progress) -> None:
        response = self.http.request(
            "GET",
            f"/ipfs/{root}",
            params={"format": "car", "dag-scope": "entity"},
            headers={"Accept": CAR_MEDIA_TYPE},
            stream=True,
        )
        try:
            _store_verified_car(root, response.iter_bytes(READ_SIZE), into, progress)
        finally:
            response.close()

    def cat(self, cid: CID | str, offset: int = 0, length: int | None = None) -> bytes:
        """Bytes through the kubo RPC, unverified: for ranges of files known to be trusted."""
        params: dict[str, Any] = {"arg": str(cid), "offset": offset}
        if length is not None:
            params["length"] = length
        return self.http.request("POST", "/api/v0/cat", params=params, signed=False).content

    def pin(self, cid: CID | str) -> None:
        self.http.request("POST", "/api/v0/pin/add", params={"arg": str(cid)})

    def unpin(self, cid: CID | str) -> None:
        self.http.request("POST", "/api/v0/pin/rm", params={"arg": str(cid)})

    def pins(self) -> dict[str, dict[str, Any]]:
        """``{cid: {"Type": ..., ...}}`` as kubo's ``pin/ls`` answers."""
        body = self.http.request("POST", "/api/v0/pin/ls", signed=False).json()
        keys = body.get("Keys", {}) if isinstance(body, dict) else {}
        return dict(keys)


def _store_verified_car(root: CID, chunks: Iterator[bytes], into: Path, progress: Progress) -> None:
    """Write each block of a CAR stream to ``into`` once it matched its CID."""
    try:
        reader = CarReader(_IteratorReader(chunks))
        if root not in reader.roots:
            raise CasError(f"the gateway's CAR is rooted at {reader.roots}, not {root}")
        for block in reader:
            (into / str(block.cid)).write_bytes(block.data)
            progress(len(block.data))
    except CarError as exc:
        raise CasError(f"refused the gateway's CAR for {root}: {exc}") from exc


def _json_line(line: str) -> dict[str, Any]:
    value = json.loads(line)
    if not isinstance(value, dict):
        raise KeyError("Hash")
    return value
