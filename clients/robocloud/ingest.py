"""Bag ingestion through the storage service: upload a bag (or name one in cas), follow the
job, and export records as MCAP or JSON lines.

A ROS 2 bag is a directory (metadata.yaml and its storage files): it goes to cas first, as a
UnixFS directory, and the storage node fetches it by CID, verifying every block.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.client import ServiceClient

UPLOAD_CHUNK = 1 << 20
FINISHED = ("succeeded", "failed")
WAIT_TIMEOUT_S = 3600.0
"""How long ``Ingest.wait`` follows a job by default: a storage node that answers "running"
forever must not hold the robot forever."""


def _file_chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as stream:
        while chunk := stream.read(UPLOAD_CHUNK):
            yield chunk


class Ingest(ServiceClient):
    """Ingest jobs and exports of the storage service."""

    default_service = "storage"

    def upload(self, bag: Path) -> dict[str, Any]:
        """Send a bag file (ROS 1 ``.bag``, ``.mcap``, ``.db3``) and return its new job."""
        digest = hashlib.sha256()
        for chunk in _file_chunks(bag):
            digest.update(chunk)
        response = self.request(
            "POST",
            "/v1/ingest",
            content=_file_chunks(bag),
            content_sha256=digest.hexdigest(),
            headers={"Content-Type": "application/octet-stream"},
            idempotent=False,
        )
        job: dict[str, Any] = self.json_of(response)
        return job

    def from_cas(self, cid: CID | str) -> dict[str, Any]:
        """Ingest a bag already in cas: a file, or a ROS 2 bag directory."""
        job: dict[str, Any] = self.post_json("/v1/ingest", {"cid": str(cid)})
        return job

    def ingest(self, bag: Path, cas: Cas | None = None) -> dict[str, Any]:
        """A bag file is uploaded; a ROS 2 bag directory goes through ``cas`` (required then)."""
        if bag.is_dir():
            if cas is None:
                raise ValueError("a ROS 2 bag directory is ingested through cas: pass cas")
            return self.from_cas(cas.add_directory(bag))
        return self.upload(bag)

    def job(self, job_id: str) -> dict[str, Any]:
        job: dict[str, Any] = self.get_json(f"/v1/jobs/{job_id}")
        return job

    def wait(
        self,
        job_id: str,
        on_progress: Callable[[dict[str, Any]], None] | None = None,
        *,
        poll_s: float = 0.25,
        timeout_s: float = WAIT_TIMEOUT_S,
    ) -> dict[str, Any]:
        """Poll a job until it succeeds or fails, or ``timeout_s`` passes; its last state
        (whose status is then still ``queued`` or ``running``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.job(job_id)
            if on_progress is not None:
                on_progress(job)
            if job["status"] in FINISHED or time.monotonic() > deadline:
                return job
            time.sleep(min(poll_s, max(deadline - time.monotonic(), 0.0)))

    def resume(self, job_id: str) -> dict[str, Any]:
        job: dict[str, Any] = self.post_json(f"/v1/jobs/{job_id}/resume")
        return job

    def bind(
        self, template: str, *, topic: str | None = None, msgtype: str | None = None
    ) -> dict[str, Any]:
        """Bind a topic or a message type to an approved template for later ingests."""
        bindings: dict[str, Any] = self.post_json(
            "/v1/bindings", {"template": template, "topic": topic, "msgtype": msgtype}
        )
        return bindings

    def export(self, params: dict[str, Any], out: Path) -> int:
        """Write a query's export (``format`` = ``mcap`` or ``jsonl``) to ``out``; its size."""
        size = 0
        response = self.request("GET", "/v1/export", params=params, stream=True)
        try:
            with out.open("wb") as handle:
                for chunk in response.iter_bytes():
                    handle.write(chunk)
                    size += len(chunk)
        finally:
            response.close()
        return size
