"""Bag ingestion through the storage service: upload a bag (or name one in cas), follow the
job, and export records as MCAP or JSON lines.

A ROS 2 bag is a directory (metadata.yaml and its storage files): it goes to cas first, as a
UnixFS directory, and the storage node fetches it by CID, verifying every block.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.client import MAX_WAIT_S, FileBody, ServiceClient
from robocloud.errors import InvalidAnswerError, RobocloudError
from robocloud.partial import free_space_beside, written_whole

FINISHED = ("succeeded", "failed")
WAIT_TIMEOUT_S = 3600.0
"""How long ``Ingest.wait`` follows a job by default: a storage node that answers "running"
forever must not hold the robot forever."""


class ExportTooLargeError(RobocloudError):
    """An export is larger than the caller allows; nothing of it is left on disk."""

    def __init__(self, limit: int) -> None:
        super().__init__(f"the export holds more than the limit of {limit} bytes")
        self.limit = limit


def _job(answer: Any) -> dict[str, Any]:
    """A job as the storage node answers it, checked for every field this SDK and the CLI
    read (id, status, message and record counts, topics, the error of a failed job), so a
    malformed one is an ``InvalidAnswerError`` rather than a ``KeyError`` later."""
    try:
        counts = [answer["messages"]["done"], answer["messages"]["total"]]
        counts.append(answer["records"]["committed"])
        if not isinstance(answer["id"], str) or not isinstance(answer["status"], str):
            raise TypeError("id or status is not text")
        counts.append(answer["updated_ns"])
        if any(isinstance(count, bool) or not isinstance(count, int) for count in counts):
            raise TypeError("a message or record count, or updated_ns, is not an integer")
        topics = answer["topics"]
        if not isinstance(topics, list) or not all(isinstance(t, dict) for t in topics):
            raise TypeError("topics is not a list of objects")
        if answer["status"] == "failed" and not isinstance(answer["error"].get("message"), str):
            raise TypeError("a failed job has no error message")
    except (AttributeError, KeyError, TypeError) as exc:
        raise InvalidAnswerError(
            f"the storage service sent a malformed ingest job ({type(exc).__name__}: "
            f"{str(exc)[:200]})"
        ) from exc
    job: dict[str, Any] = answer
    return job


def _job_of(job_id: str, answer: Any) -> dict[str, Any]:
    """The job ``answer`` holds, which must be ``job_id``: ``wait`` would otherwise report
    another job's outcome (a success) as this one's."""
    job = _job(answer)
    if job["id"] != job_id:
        raise InvalidAnswerError(
            f"asked for ingest job {job_id[:100]!r}, the storage service sent {job['id'][:100]!r}"
        )
    return job


class Ingest(ServiceClient):
    """Ingest jobs and exports of the storage service."""

    default_service = "storage"

    def upload(self, bag: Path) -> dict[str, Any]:
        """Send a bag file (ROS 1 ``.bag``, ``.mcap``, ``.db3``) and return its job: a new
        one, or this robot's job of the same bag while that one is still running. Resent
        after a broken exchange or a proxy's 502 or 504, as the node answers a resend with
        the running job and ingests no topic of a bag twice for one robot."""
        response = self.request(
            "POST",
            "/v1/ingest",
            content=FileBody(bag),
            headers={"Content-Type": "application/octet-stream"},
            idempotent=True,
        )
        return _job(self.json_of(response))

    def from_cas(self, cid: CID | str) -> dict[str, Any]:
        """Ingest a bag already in cas: a file, or a ROS 2 bag directory. Resent after a
        broken exchange or a proxy's 502 or 504: the node answers a resend with the job the
        first request made, and ingests no topic of a bag twice for one robot."""
        return _job(self.post_json("/v1/ingest", {"cid": str(cid)}, idempotent=True))

    def ingest(self, bag: Path, cas: Cas | None = None) -> dict[str, Any]:
        """A bag file is uploaded; a ROS 2 bag directory goes through ``cas`` (required then)."""
        if bag.is_dir():
            if cas is None:
                raise ValueError("a ROS 2 bag directory is ingested through cas: pass cas")
            return self.from_cas(cas.add_directory(bag))
        return self.upload(bag)

    def job(self, job_id: str, *, after_ns: int | None = None, wait_s: float = 0) -> dict[str, Any]:
        """An ingest job. With ``after_ns`` (its ``updated_ns`` as last read) and ``wait_s``
        (at most ``MAX_WAIT_S``), a long poll: the node answers as soon as the job changes
        or is finished, else with it unchanged after ``wait_s``."""
        if not 0 <= wait_s <= MAX_WAIT_S:
            raise ValueError(f"wait_s must be between 0 and {MAX_WAIT_S:g} s, not {wait_s}")
        params: dict[str, int | float] = {}
        if after_ns is not None:
            params["after_ns"] = after_ns
        if wait_s:
            params["wait_s"] = wait_s
        path = f"/v1/jobs/{quote(job_id, safe='')}"
        return _job_of(job_id, self.get_json(path, params=params or None))

    def wait(
        self,
        job_id: str,
        on_progress: Callable[[dict[str, Any]], None] | None = None,
        *,
        poll_s: float = 0.25,
        timeout_s: float = WAIT_TIMEOUT_S,
    ) -> dict[str, Any]:
        """Follow a job until it succeeds or fails, or ``timeout_s`` passes; its last state
        (whose status is then still ``queued``, ``staging`` or ``committing``).

        Each read waits on the node for the job's next change (a long poll), so a job queued
        behind others or committing a long batch costs a request every ``MAX_WAIT_S``, and
        its end is seen at once; reads are at least ``poll_s`` apart all the same, however
        often the job changes (or a node that does not wait answers)."""
        deadline = time.monotonic() + timeout_s
        asked = time.monotonic()
        job = self.job(job_id)
        while True:
            if on_progress is not None:
                on_progress(job)
            if job["status"] in FINISHED or time.monotonic() >= deadline:
                return job
            time.sleep(max(0.0, min(asked + poll_s, deadline) - time.monotonic()))
            asked = time.monotonic()
            if asked >= deadline:
                return job
            wait_s = min(MAX_WAIT_S, deadline - asked)
            job = self.job(job_id, after_ns=job["updated_ns"], wait_s=wait_s)

    def resume(self, job_id: str) -> dict[str, Any]:
        return _job_of(job_id, self.post_json(f"/v1/jobs/{quote(job_id, safe='')}/resume"))

    def bind(
        self, template: str, *, topic: str | None = None, msgtype: str | None = None
    ) -> dict[str, Any]:
        """Bind a topic or a message type to an approved template for later ingests."""
        bindings = self.post_json(
            "/v1/bindings", {"template": template, "topic": topic, "msgtype": msgtype}
        )
        if not isinstance(bindings, dict):
            raise InvalidAnswerError(
                f"the storage service's binding {str(bindings)[:100]!r} is not an object"
            )
        return bindings

    def export(
        self,
        params: dict[str, Any],
        out: Path,
        *,
        max_size: int | None = None,
        overwrite: bool = True,
    ) -> int:
        """Write a query's export (``format`` = ``mcap`` or ``jsonl``) to ``out``; its size.

        ``out`` is replaced only by a whole export: one that fails midway (a refusal, a
        broken or too slow answer, one past ``max_size``) leaves it as it was. Without
        ``overwrite``, an ``out`` that exists when the export is complete is kept
        (``FileExistsError``). An export
        declares no size and a node may stream one without end, so at most ``max_size``
        bytes are written (``ExportTooLargeError`` past it), by default the free space in
        ``out``'s directory when the export starts."""
        limit = free_space_beside(out) if max_size is None else max_size
        size = 0
        with (
            written_whole(out, overwrite=overwrite) as handle,
            self.translate_errors("GET", f"{self.base_url}/v1/export"),
        ):
            response = self.request("GET", "/v1/export", params=params, stream=True)
            try:
                for chunk in response.iter_bytes():
                    size += len(chunk)
                    if size > limit:
                        raise ExportTooLargeError(limit)
                    handle.write(chunk)
            finally:
                response.close()
        return size
