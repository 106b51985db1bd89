"""Bag ingestion jobs: a bag in, records out, nothing half-ingested.

The record logs are append-only and anchored, so an ingest cannot be rolled back once it has
written; it is therefore built so that it either writes nothing or can always be finished:

1. **stage**: the whole bag is read, every bound message converted and validated against its
   approved template, image/file bytes stored in cas, and the records spooled per template in
   the job's directory, with the documents their views keep (a large bag is staged by several
   processes, a time window each: :mod:`services.storage.staging`), and synced before the job
   saves them as staged. Any failure here (a truncated bag, an undecodable message, a value a
   template refuses) fails the job with nothing appended; cas blobs are content-addressed and
   harmless.
2. **commit**: each template's spool is appended through ``RecordStore.append_prepared`` in
   batches.
   Before a batch the job durably records its intent (template, spool offset, count, log size
   before); after it, the new offset. A job interrupted anywhere (kill -9 included) resumes at
   the next start: a pending intent is settled by looking in the template's log, past the
   recorded size, for entries whose ``meta`` is this job's authorship (each signed request's
   nonce is unique), so no batch is lost or appended twice. A spool found damaged all the same
   (its records are checked against the staged count and each other) is staged again from the
   bag, and the commit goes on past the records already committed.

Topics whose type no approved template binds are reported, not ingested; so are topics the
same robot has ingested from the same bag before (:mod:`services.storage.ingested`), and a
bag sent again while its job is still running gets that job.
"""

from __future__ import annotations

import hashlib
import heapq
import json
import logging
import queue
import secrets
import shutil
import tempfile
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

from robocloud.templates import TemplateInvalid, parse_template, recordable_topic
from services.common.changes import Changes
from services.common.disk import DiskReserve
from services.common.durable import atomic_write, fsync_dir
from services.storage.bags import Bag, BagConnection
from services.storage.catalog import CatalogError
from services.storage.ingested import IngestedBags, IngestedRow, IngestedTopic
from services.storage.matcher import (
    Bindings,
    DraftError,
    draft_template,
)
from services.storage.recordlog import RecordLogs
from services.storage.recordstore import Authorship, Offload, RecordStore, record_id
from services.storage.staging import (
    STALL_S,
    IngestFailed,
    Plans,
    SpoolDamaged,
    SpoolReader,
    StagingProcesses,
    bag_failures,
    check_complete,
    compile_plan,
    job_failure,
    start_workers_server,
)

log = logging.getLogger("robocloud.storage.ingest")

Status = Literal["queued", "staging", "committing", "succeeded", "failed"]
Due = Literal["publish", "expire"]
JOB_ID_BYTES = 12
PUBLISH_ATTEMPTS = 8
"""Attempts to publish a job's dataset before the node gives up and removes the bag."""
PUBLISH_RETRY_S = 5.0
"""The wait after the first failed attempt; it doubles after each, up to
:data:`PUBLISH_RETRY_MAX_S`: the eight attempts span about ten minutes of an outage."""
PUBLISH_RETRY_MAX_S = 600.0
KEEP_RESUMABLE_S = 7 * 24 * 3600.0
"""How long a job that failed while committing keeps its bag and spool for a resume."""
INCOMING = "incoming"
"""Under the jobs' root: bags on their way in, each in a directory of its own
(:meth:`IngestJobs.incoming`)."""
MAX_WAITERS_PER_JOB = 16
"""Requests waiting on one job's next change at once (``GET /v1/jobs/{id}?wait_s=``); more
answer at once, as without a wait. Only a job still queued or running has waits, so the
node holds at most this many times its pending jobs (``max_pending``)."""


class JobNotFound(LookupError):
    def __init__(self, job_id: str) -> None:
        super().__init__(f"no ingest job {job_id[:64]!r}")
        self.job_id = job_id


class JobNotResumable(Exception):
    def __init__(self, job_id: str, status: str) -> None:
        super().__init__(
            f"ingest job {job_id} is {status}; only a job failed while committing resumes"
        )
        self.job_id = job_id
        self.status = status


class BagAwaitsResume(Exception):
    """The robot's earlier job of this bag failed while committing: some of its records are
    in, and only resuming that job adds the rest exactly once."""

    def __init__(self, job_id: str, bag: str) -> None:
        super().__init__(
            f"ingest job {job_id} of this bag ({bag}) failed while committing and can be "
            "resumed: resume it rather than ingest the bag again"
        )
        self.job_id = job_id
        self.bag = bag


class TooManyJobs(Exception):
    """No place for one more job: the service holds ``limit`` queued or running (``per``
    ``service``), or the robot holds its share of them (``per`` ``robot``)."""

    def __init__(self, limit: int, per: Literal["service", "robot"]) -> None:
        message = (
            f"{limit} ingest jobs are queued or running; try again later"
            if per == "service"
            else f"this robot has {limit} ingest jobs queued or running, its share of the "
            "service's; send the next once one has finished"
        )
        super().__init__(message)
        self.limit = limit
        self.per = per


@dataclass
class TopicReport:
    topic: str
    msgtype: str
    messages: int
    template: str | None = None
    skipped: str | None = None
    """Why this topic is not ingested (no approved template bound, no definition, ingested
    from this bag before)."""
    ingested_by: str | None = None
    """The earlier job of the same robot that ingested this topic of this bag into
    ``template``: this job skipped it."""
    draft: dict[str, Any] | None = None
    """For a topic bound to no template, one generated from its message definition: the
    designer edits and submits it (``POST /v1/templates``) and binds it."""
    fits: list[str] = field(default_factory=list)
    """Approved templates with the draft's fields, oldest first: the topic can be bound to
    one of them as it is."""


@dataclass
class Job:
    id: str
    bag: str
    """What was ingested: ``cid:<cid>`` or ``upload:<sha256>``."""
    author: dict[str, Any]
    status: Status = "queued"
    messages_total: int = 0
    messages_done: int = 0
    records_staged: int = 0
    records_committed: int = 0
    topics: list[TopicReport] = field(default_factory=list)
    error: dict[str, Any] | None = None
    content: str | None = None
    """``sha256:<hex>`` of a bag that is one file, once known: what the node remembers this
    robot ingested (:func:`_bag_key`), so that a file sent once uploaded and once by a CID, or
    by two CIDs of two imports, is one bag."""
    record_ids: dict[str, list[str]] = field(default_factory=dict)
    """Per template, the first and last record id committed."""
    staged: dict[str, int] = field(default_factory=dict)
    spool_parts: int = 1
    """Spool files per template: one per staging window."""
    committed: dict[str, int] = field(default_factory=dict)
    intent: dict[str, Any] | None = None
    dataset: dict[str, Any] | None = None
    """What publishing the ingested dataset gave: the bag's CID, its description's CID and the
    advertisement's transaction, or the error that stopped it (the records stay committed)."""
    publish_attempts: int = 0
    """Times publishing the dataset began, each saved before it: above 1, an earlier attempt
    was cut short (kill -9, power cut) or failed and may have advertised the dataset, so the
    publisher looks on chain for that advertisement before it makes one."""
    publish_retry_ns: int | None = None
    """When the next attempt to publish is due (wall clock, ns, so that it survives a
    restart), after one failed; None when none is. The bag is kept until then."""
    advertise_tx: dict[str, Any] | None = None
    """The advertise transaction the publisher signed (``SignedTransaction.to_json``), saved
    before it was sent: a later attempt sends these same bytes again and waits for them, since
    behind an external node one still pending when the node died was not found on chain and a
    second advertisement was signed, both then mined."""
    created_ns: int = field(default_factory=time.time_ns)
    updated_ns: int = field(default_factory=time.time_ns)

    def to_json(self) -> dict[str, Any]:
        """The public view (``GET /v1/jobs/{id}``)."""
        return {
            "id": self.id,
            "bag": self.bag,
            "signer": self.author.get("signer"),
            "status": self.status,
            "messages": {"done": self.messages_done, "total": self.messages_total},
            "records": {"staged": self.records_staged, "committed": self.records_committed},
            "topics": [asdict(topic) for topic in self.topics],
            "unbound_topics": [t.topic for t in self.topics if t.template is None],
            "record_ids": self.record_ids,
            "dataset": self._dataset_view(),
            "error": self.error,
            "created_ns": self.created_ns,
            "updated_ns": self.updated_ns,
        }

    def _dataset_view(self) -> dict[str, Any] | None:
        """The dataset, or why it is not published: after how many attempts, and when the
        next is due while one is."""
        if self.dataset is None or "error" not in self.dataset:
            return self.dataset
        view = {**self.dataset, "attempts": self.publish_attempts}
        if self.publish_retry_ns is not None:
            view["next_attempt_ns"] = self.publish_retry_ns
        return view

    def copy(self) -> Job:
        """A deep copy, for a reader outside the jobs' lock."""
        return Job.from_json(json.loads(json.dumps(asdict(self))))

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> Job:
        topics = [TopicReport(**topic) for topic in document.pop("topics")]
        return cls(topics=topics, **document)


class DatasetUnpublishable(Exception):
    """A dataset no later attempt can publish: the node's own rules refuse its description
    (past a bound, invalid), and they refuse it the same way each time. Its job gives up at
    once rather than keep the bag through every retry of an outage."""


class Publish(Protocol):
    """Describes and advertises a job's dataset once its records are committed; what it
    published, for the job's report. ``save_advertise_tx`` durably saves the advertise
    transaction (``Job.advertise_tx``) before it is sent."""

    def __call__(
        self, job: Job, bag: Path, save_advertise_tx: Callable[[dict[str, Any]], None]
    ) -> dict[str, Any]: ...


UNRECORDABLE_TOPIC = (
    "its name is not one a record holds: / and at most 256 of A-Z a-z 0-9 _ / ~ . -"
)
"""Why a topic is skipped whose name no record may hold (a space, a letter outside ASCII, a
thousand characters): its records failed the whole job, every other topic's with them."""


def _name_drafts_apart(reports: list[TopicReport]) -> None:
    """Give each distinct draft of a job its own name: a draft is named after its type's
    last part, so ``sensor_msgs/msg/Imu`` and ``my_msgs/msg/Imu`` both drafted ``imu``, and
    the second was lost to ``--drafts`` (one file a name). Topics of one type keep sharing
    their one draft. Linear in the drafts, however many share a name."""
    taken: set[str] = set()
    named: dict[str, str] = {}
    """Each distinct draft (its JSON) and the name it got."""
    suffixes: dict[str, int] = {}
    for report in reports:
        if report.draft is None:
            continue
        base = report.draft["name"]
        content = json.dumps(report.draft, sort_keys=True)
        name = named.get(content)
        if name is None:
            name = base
            while name in taken:
                suffixes[base] = suffixes.get(base, 1) + 1
                name = f"{base[: 62 - len(str(suffixes[base]))]}_{suffixes[base]}"
            taken.add(name)
            named[content] = name
        report.draft = {**report.draft, "name": name}


def _unbound(connection: BagConnection) -> str:
    """Why a topic bound to no template is skipped, and why it has no draft when its type
    cannot be decoded: binding it would fail the job (``message_type_undefined``)."""
    unbound = "no template is bound to this topic or message type"
    if connection.problem is None:
        return unbound
    return f"{unbound}, and its type cannot be decoded: {connection.problem}"


def _draft(connection: BagConnection) -> dict[str, Any] | None:
    """The draft template a connection's definition gives, when it gives one."""
    if connection.typestore is None:
        return None
    try:
        return draft_template(connection.typestore, connection.msgtype)
    except DraftError:
        return None


def _bag_in(directory: Path) -> Path:
    """A job's bag: ``bag`` (a ROS 2 directory, a ROS 1 file) or ``bag.mcap``/``bag.db3``, as
    rosbags picks the storage plugin of a bare file by its suffix."""
    return next(directory.glob("bag*"), directory / "bag")


def _awaits_bag(job: Job) -> bool:
    """A job failed while committing and not resumed in time: part of its records are in,
    its bag was removed, and only the bag sent again finishes it (a job failed before it
    committed has staged nothing, and one failed while committing stays resumable until
    then)."""
    return job.status == "failed" and bool(job.staged) and not (job.error or {}).get("resumable")


def _messages_in(bag: Bag, plans: Plans) -> int:
    """The messages of ``bag`` that ``plans`` stage."""
    return sum(c.count for c in bag.connections if (c.topic, c.msgtype) in plans)


def _job_document(job: Job) -> bytes:
    """What job.json holds of ``job``."""
    return json.dumps(asdict(job)).encode()


def _ingested_rows(job: Job) -> list[IngestedRow]:
    """The topics a job committed, for :class:`IngestedBags`."""
    topics: list[IngestedTopic] = [
        (report.topic, report.msgtype, report.template)
        for report in job.topics
        if report.template is not None and report.skipped is None
    ]
    return [(job.author["signer"], _bag_key(job), topic, job.id) for topic in topics]


def _bag_key(job: Job) -> str:
    """The bag a job ingests, as :class:`IngestedBags` remembers it: a file by its bytes
    (``sha256:<hex>``) however it came, a ROS 2 directory by its CID."""
    return job.content or _uploaded_content(job) or job.bag


def _uploaded_content(job: Job) -> str | None:
    """An upload's ``sha256:<hex>``, taken as it arrived (``upload:<hex>``)."""
    kind, _, value = job.bag.partition(":")
    return f"sha256:{value}" if kind == "upload" else None


def _content_of(job: Job, bag: Path) -> str | None:
    """``sha256:<hex>`` of a bag that is one file; None for a ROS 2 directory."""
    uploaded = _uploaded_content(job)
    if uploaded is not None or not bag.is_file():
        return uploaded
    with bag.open("rb") as handle:
        return f"sha256:{hashlib.file_digest(handle, 'sha256').hexdigest()}"


def _remove(path: Path) -> None:
    """Remove a bag, file or directory, so that a finished job keeps no copy of it."""
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


class IngestJobs:
    """Ingest jobs on one worker thread, persisted under ``root`` and resumed at open."""

    def __init__(
        self,
        root: Path,
        store: RecordStore,
        logs: RecordLogs,
        bindings: Bindings,
        blobs: Callable[[], Offload],
        *,
        batch_records: int = 5000,
        staging_workers: int = 1,
        parallel_from_messages: int = 20_000,
        worker_memory_bytes: int = 0,
        stall_s: float = STALL_S,
        max_pending: int = 16,
        max_pending_per_robot: int = 4,
        keep_finished: int = 1000,
        publish: Publish | None = None,
        publish_attempts: int = PUBLISH_ATTEMPTS,
        publish_retry_s: float = PUBLISH_RETRY_S,
        keep_resumable_s: float = KEEP_RESUMABLE_S,
        disk_reserve: DiskReserve | None = None,
    ) -> None:
        self.root = root
        self.store = store
        self.logs = logs
        self.bindings = bindings
        self.blobs = blobs
        self.batch_records = batch_records
        self.staging_workers = staging_workers
        """Processes that stage a bag of at least ``parallel_from_messages`` messages, each a
        time window of it (see :mod:`services.storage.staging`); one of them stages a smaller
        bag."""
        self.parallel_from_messages = parallel_from_messages
        self.worker_memory_bytes = worker_memory_bytes
        """The address space of each staging process (0: unbounded)."""
        self.stall_s = stall_s
        """A staging process silent this long is stuck (:data:`~staging.STALL_S`)."""
        self.max_pending = max_pending
        self.max_pending_per_robot = max_pending_per_robot
        self.keep_finished = keep_finished
        self.publish = publish
        """Describes and advertises what a job ingested, once its records are committed."""
        self.publish_attempts = publish_attempts
        self.publish_retry_s = publish_retry_s
        self.keep_resumable_s = keep_resumable_s
        """How long a job failed while committing keeps its inputs for a resume: nobody may
        ever resume it, and each kept a bag of up to 16 GiB and its spool until a thousand
        later jobs had finished."""
        self.disk_reserve = disk_reserve or DiskReserve(root, 0)
        """Kept free between the job's writes: a bag of a few hundred kB that passed the
        request's check stages and commits records, indexes and logs of several times its
        size, which took the disk's last bytes and left the robots' deletions no room."""
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._lock = threading.Lock()
        """Held to read or change jobs in memory, never while a job is written to disk: a
        poll waited for the ingest thread's fsyncs, one batch of records each."""
        self._saving = threading.Lock()
        """Held, before :attr:`_lock`, from a change to its save, so that job.json is
        written in the order its changes were made."""
        self._changes: dict[str, Changes] = {}
        """Each job's changes, for the long polls of it (:meth:`changes_of`)."""
        self._waits_stopped = False
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._due: list[tuple[int, str, Due]] = []
        """What the worker thread does to a finished job at a time: publish a succeeded
        job's dataset again, or drop the inputs of a failed job nobody resumed: (when, job
        id, what), a heap the worker thread alone uses once it runs."""
        root.mkdir(parents=True, exist_ok=True)
        self.ingested = IngestedBags(root / "ingested.sqlite")
        # A bag on its way in when the service stopped (kill -9 during an upload) is no job's.
        shutil.rmtree(self.root / INCOMING, ignore_errors=True)
        start_workers_server()
        for path in sorted(root.glob("*/job.json"), key=lambda p: p.stat().st_mtime):
            job = Job.from_json(json.loads(path.read_text()))
            self._jobs[job.id] = job
            if job.status not in ("succeeded", "failed"):
                self._queue.put(job.id)
            elif job.status == "failed" and not (job.error or {}).get("resumable"):
                self._drop_inputs(job)
            elif job.status == "failed":
                self._expire_later(job)
            elif job.publish_retry_ns is not None:
                heapq.heappush(self._due, (job.publish_retry_ns, job.id, "publish"))
        if self.ingested.created:
            self.ingested.add(
                row
                for job in self._jobs.values()
                if job.status == "succeeded"
                for row in _ingested_rows(job)
            )
        self._worker = threading.Thread(target=self._work, name="storage-ingest", daemon=True)
        self._worker.start()

    def close(self) -> None:
        self.stop_waits()
        self._queue.put(None)
        self._worker.join()
        self.ingested.close()

    @contextmanager
    def incoming(self) -> Iterator[Path]:
        """A new directory for one bag on its way in (an upload, a bag fetched from cas),
        removed when the block ends whatever happened.

        :meth:`submit` moves the bag out of it, which left the directory behind, empty, after
        every accepted upload; a bag refused after it arrived (429 ``too_many_jobs``) was left
        whole.
        """
        incoming = self.root / INCOMING
        incoming.mkdir(exist_ok=True)
        spool = Path(tempfile.mkdtemp(dir=incoming, prefix=".bag-"))
        try:
            yield spool
        finally:
            shutil.rmtree(spool, ignore_errors=True)

    def admit(self, signer: str) -> None:
        """Raise :class:`TooManyJobs` unless a job of ``signer``'s would have a place now.
        Asked before a bag is received, so that a robot refused is refused before it sends
        gigabytes; :meth:`submit` asks again."""
        with self._lock:
            self._admit(signer)

    def unfinished(self, signer: str, source: str) -> Job | None:
        """:meth:`_unfinished`, asked before a bag is received, so that a robot resending a
        bag whose job runs gets the job at once; :meth:`submit` asks again."""
        with self._lock:
            job = self._unfinished(signer, source)
            return None if job is None else job.copy()

    def _unfinished(self, signer: str, source: str) -> Job | None:
        """``signer``'s job of the bag ``source`` that is queued or running, if any;
        :class:`BagAwaitsResume` where one failed while committing and may be resumed."""
        for job in self._jobs_of(signer, source):
            if job.status not in ("succeeded", "failed"):
                return job
            if job.status == "failed" and (job.error or {}).get("resumable"):
                raise BagAwaitsResume(job.id, source)
        return None

    def _awaiting_bag(self, signer: str, source: str) -> Job | None:
        """``signer``'s job of the bag ``source`` that awaits the bag (:func:`_awaits_bag`).
        A new job of the bag appended again every record the old one had committed."""
        return next((job for job in self._jobs_of(signer, source) if _awaits_bag(job)), None)

    def _jobs_of(self, signer: str, source: str) -> Iterator[Job]:
        robot = signer.lower()
        for job in self._jobs.values():
            if job.bag == source and job.author["signer"].lower() == robot:
                yield job

    def _admit(self, signer: str) -> None:
        pending = [j for j in self._jobs.values() if j.status not in ("succeeded", "failed")]
        if len(pending) >= self.max_pending:
            raise TooManyJobs(self.max_pending, "service")
        robot = signer.lower()
        if sum(j.author["signer"].lower() == robot for j in pending) >= self.max_pending_per_robot:
            raise TooManyJobs(self.max_pending_per_robot, "robot")

    def submit(self, bag: Path, source: str, author: Authorship) -> Job:
        """Take ownership of ``bag`` (moved into the job's directory) and queue its ingest;
        or, when the robot's earlier job of the same bag is still queued or running, leave
        ``bag`` and answer that job (:class:`BagAwaitsResume` where it failed resumable).
        The robot's job of the bag that awaits it takes it and goes on committing."""
        with self._saving, self._lock:
            earlier = self._unfinished(author.signer, source)
            if earlier is not None:
                return earlier.copy()
            self._admit(author.signer)
            job = self._awaiting_bag(author.signer, source)
            if job is None:
                job = Job(id=secrets.token_hex(JOB_ID_BYTES), bag=source, author=asdict(author))
                (self.root / job.id).mkdir()
            else:
                job.status, job.error = "committing", None
                self._jobs.move_to_end(job.id)
            shutil.move(str(bag), self.root / job.id / f"bag{bag.suffix}")
            self._save(job)
            self._jobs[job.id] = job
            self._forget_old()
            queued = job.copy()
        self._queue.put(job.id)
        return queued

    def resume(self, job_id: str) -> Job:
        """Queue again a job that failed while committing (cas or disk trouble, say)."""
        with self._saving, self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                raise JobNotFound(job_id)
            if job.status != "failed" or not (job.error or {}).get("resumable"):
                raise JobNotResumable(job_id, job.status)
            self._admit(job.author["signer"])
            job.status, job.error = "committing", None
            self._save(job)
        self._queue.put(job_id)
        return self.get(job_id)

    def changes_of(self, job_id: str) -> Changes:
        """What a long poll of ``job_id`` waits on: advanced at each change of that job
        alone, as one ``Changes`` for every job woke every wait at each progress report of
        any bag (docs/storage.md has the figures). Like :meth:`peek`, read without the lock
        on the event loop; made by the first read that waits, it goes when the job is
        forgotten."""
        self.peek(job_id)
        changes = self._changes.get(job_id)
        if changes is None:
            changes = self._changes.setdefault(job_id, Changes(MAX_WAITERS_PER_JOB))
            if self._waits_stopped:
                changes.close()
        return changes

    def stop_waits(self) -> None:
        """Answer every long poll now and each later one at once (the node is stopping)."""
        self._waits_stopped = True
        for changes in list(self._changes.values()):
            changes.close()

    def peek(self, job_id: str) -> tuple[int, Status]:
        """A job's ``updated_ns`` and status, cheap enough for every wake of every long poll:
        read on the event loop without the lock (each one attribute, which a writer sets
        whole), where :meth:`get` deep-copies the job (its topics and their drafts) under
        it, which waits woken at each progress report would have done each time."""
        job = self._jobs.get(job_id)
        if job is None:
            raise JobNotFound(job_id)
        return job.updated_ns, job.status

    def get(self, job_id: str) -> Job:
        with self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                raise JobNotFound(job_id)
            return job.copy()

    def wait(self, job_id: str, timeout_s: float) -> Job:
        """The job once finished and saved (for tests), or as it is at ``timeout_s``.
        Readers see a change before job.json holds it (:meth:`_update`); taking
        :attr:`_saving` once the job is seen finished waits for that save."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.get(job_id)
            if job.status in ("succeeded", "failed"):
                with self._saving:
                    return self.get(job_id)
            if time.monotonic() > deadline:
                return job
            time.sleep(0.05)

    def _forget_old(self) -> None:
        """Forget finished jobs past the last :attr:`keep_finished`, but those that retry
        publishing or await their bag."""
        finished = [
            j.id
            for j in self._jobs.values()
            if j.status in ("succeeded", "failed")
            and j.publish_retry_ns is None
            and not _awaits_bag(j)
        ]
        for job_id in finished[: max(0, len(finished) - self.keep_finished)]:
            del self._jobs[job_id]
            forgotten = self._changes.pop(job_id, None)
            if forgotten is not None:
                forgotten.close()
            shutil.rmtree(self.root / job_id, ignore_errors=True)

    def _save(self, job: Job) -> None:
        job.updated_ns = time.time_ns()
        self._write(job, _job_document(job))
        self._advance(job.id)

    def _write(self, job: Job, document: bytes) -> None:
        atomic_write(self.root / job.id / "job.json", document)

    def _update(self, job: Job, *, save: bool = True, **changes: Any) -> None:
        """Change a job; readers see it at once, job.json (two fsyncs) only if ``save``,
        written once readers may read again."""
        with self._saving:
            with self._lock:
                for key, value in changes.items():
                    setattr(job, key, value)
                job.updated_ns = time.time_ns()
                document = _job_document(job) if save else None
            if document is not None:
                self._write(job, document)
        self._advance(job.id)

    def _advance(self, job_id: str) -> None:
        changes = self._changes.get(job_id)
        if changes is not None:
            changes.advance()

    def _work(self) -> None:
        """Run queued jobs one at a time, for the service's lifetime. A job whose failure
        cannot be saved either (a full disk) is logged and left failed in memory, to be
        resumed from its last saved state at the next start: raising out of here killed
        the only ingest thread, and every later job stayed queued."""
        while (next_job := self._next_job()) is not None:
            job_id, due = next_job
            job = self._jobs.get(job_id)
            if job is None:
                continue
            try:
                if due == "publish":
                    self._publish_again(job)
                elif due == "expire":
                    self._expire(job)
                else:
                    self._attempt(job)
            except Exception:
                log.exception("ingest job's failure not saved", extra={"job": job.id})

    def _next_job(self) -> tuple[str, Due | None] | None:
        """The next job queued, or else, once it is due, the next finished job with
        something due (:attr:`_due`); None when the jobs close. Queued jobs (and the close)
        come first, so retries due while a cas outage lasts hold up neither."""
        while True:
            timeout = None
            if self._due:
                timeout = max(0.0, (self._due[0][0] - time.time_ns()) / 1e9)
            try:
                job_id = self._queue.get(timeout=timeout)
            except queue.Empty:
                if self._due[0][0] <= time.time_ns():
                    _, job_id, due = heapq.heappop(self._due)
                    return job_id, due
                continue
            return None if job_id is None else (job_id, None)

    def _attempt(self, job: Job) -> None:
        try:
            self._run(job)
        except Exception as exc:
            failure = job_failure(exc)
            if failure is None:
                log.exception("ingest job failed", extra={"job": job.id})
                failure = IngestFailed("ingest_failed", f"{type(exc).__name__}: {exc}", {})
            self._fail(job, failure.code, str(failure), failure.details)

    def _fail(self, job: Job, code: str, message: str, details: dict[str, Any]) -> None:
        """Save the job as failed. One that cannot be resumed keeps neither its spool nor its
        bag (:meth:`_drop_inputs`): the spool goes before the failure is saved, which a full
        disk needs the room for, the bag only after, since a job whose failure was not saved
        runs again at the next start."""
        if code == "insufficient_storage":
            log.error("ingest job failed: %s", message, extra={"job": job.id})
        resumable = job.status == "committing"
        error = {"code": code, "message": message, "details": details, "resumable": resumable}
        if resumable:
            error["resumable_until_ns"] = time.time_ns() + self._keep_resumable_ns
        else:
            shutil.rmtree(self.root / job.id / "staged", ignore_errors=True)
        self._update(job, status="failed", error=error)
        if resumable:
            self._expire_later(job)
        else:
            _remove(_bag_in(self.root / job.id))

    def _expire_later(self, job: Job) -> None:
        """Have the worker drop a resumable job's inputs once its time to be resumed is out."""
        heapq.heappush(self._due, (self._resumable_until(job), job.id, "expire"))

    def _resumable_until(self, job: Job) -> int:
        """When a failed job's time to be resumed is out; a job saved before that time was
        recorded has it from its last save."""
        fallback = job.updated_ns + self._keep_resumable_ns
        return int((job.error or {}).get("resumable_until_ns", fallback))

    @property
    def _keep_resumable_ns(self) -> int:
        return int(self.keep_resumable_s * 1e9)

    def _expire(self, job: Job) -> None:
        """Drop the bag and spool of a job nobody resumed in time; it is then failed for
        good, its committed records kept. A job resumed since (and failed again, with a
        later time) is left alone. Checked and saved under the lock, so that no resume
        starts in between; once saved, none starts at all."""
        with self._saving, self._lock:
            error = job.error or {}
            if job.status != "failed" or not error.get("resumable"):
                return
            if self._resumable_until(job) > time.time_ns():
                return
            job.error = {
                **error,
                "resumable": False,
                "message": f"{error['message']}; not resumed within "
                f"{self.keep_resumable_s:g} s, its bag was removed: the bag sent again "
                "finishes the job",
            }
            self._save(job)
        self._drop_inputs(job)

    def _drop_inputs(self, job: Job) -> None:
        """What a failed job that cannot be resumed left, its failure saved: a robot sends the
        bag again. Bags of failed jobs were kept until a thousand later jobs had finished, so
        one robot sending bags that fail (16 GiB each at most) could fill the disk."""
        shutil.rmtree(self.root / job.id / "staged", ignore_errors=True)
        _remove(_bag_in(self.root / job.id))

    def _run(self, job: Job) -> None:
        if job.status in ("queued", "staging"):
            self._stage(job)
        self._commit(job)
        self.ingested.add(_ingested_rows(job))
        if self.publish is not None and job.records_committed and job.dataset is None:
            self._publish(job, self.publish)
        shutil.rmtree(self.root / job.id / "staged", ignore_errors=True)
        self._drop_bag_unless_retrying(job)
        self._update(job, status="succeeded")

    def _publish_again(self, job: Job) -> None:
        """A succeeded job's next attempt to publish its dataset; the bag goes once none is
        left (publishing turned off since the last start leaves none)."""
        if job.publish_retry_ns is None:
            return
        if self.publish is not None:
            self._publish(job, self.publish)
        else:
            self._update(job, publish_retry_ns=None)
        self._drop_bag_unless_retrying(job)

    def _drop_bag_unless_retrying(self, job: Job) -> None:
        """A finished job keeps its bag only while a publish retry needs it."""
        if job.publish_retry_ns is None:
            _remove(_bag_in(self.root / job.id))

    def _publish(self, job: Job, publish: Publish) -> None:
        """Publish the job's dataset; a failure is reported with the job, which succeeded,
        and tried again later (a cas or ledger outage) while attempts are left.

        The attempt is saved before it and its outcome after, while the bag is still there: a
        job cut short once its outcome was saved neither advertises again nor needs its bag,
        and one cut short within tells the publisher so (``publish_attempts``), and what
        transaction it signed (``advertise_tx``). A retry's due time is cleared only with its
        outcome, so a retry cut short is made again at the next start."""
        self._update(job, publish_attempts=job.publish_attempts + 1)

        def save_advertise_tx(signed: dict[str, Any]) -> None:
            self._update(job, advertise_tx=signed)

        retry_ns = None
        try:
            dataset = publish(job, _bag_in(self.root / job.id), save_advertise_tx)
        except DatasetUnpublishable as exc:
            dataset = {"error": str(exc)[:500]}
            log.warning("dataset cannot be published", extra={"job": job.id, "error": str(exc)})
        except Exception as exc:
            dataset = {"error": str(exc)[:500]}
            retry_ns = self._publish_retry_ns(job)
            log.warning(
                "dataset not published",
                extra={
                    "job": job.id,
                    "error": str(exc),
                    "attempts": job.publish_attempts,
                    "retry": retry_ns is not None,
                },
            )
        self._update(job, dataset=dataset, publish_retry_ns=retry_ns)
        if retry_ns is not None:
            heapq.heappush(self._due, (retry_ns, job.id, "publish"))

    def _publish_retry_ns(self, job: Job) -> int | None:
        """When to try publishing again after ``job``'s latest attempt failed; None once its
        attempts are spent."""
        if job.publish_attempts >= self.publish_attempts:
            return None
        wait_s = min(self.publish_retry_s * 2 ** (job.publish_attempts - 1), PUBLISH_RETRY_MAX_S)
        return time.time_ns() + int(wait_s * 1e9)

    def _plan(self, bag: Bag, job: Job) -> tuple[list[TopicReport], Plans]:
        """Each topic's report, and the plans of those to ingest: bound to an approved
        template, and not ingested from this bag by an earlier job of the same robot."""
        reports: list[TopicReport] = []
        plans: Plans = {}
        earlier = self.ingested.ingested(job.author["signer"], _bag_key(job))
        for connection in bag.connections:
            report = TopicReport(connection.topic, connection.msgtype, connection.count)
            reports.append(report)
            if not recordable_topic(connection.topic):
                report.skipped = UNRECORDABLE_TOPIC
                continue
            template_id = self.bindings.resolve(connection.topic, connection.msgtype)
            if template_id is None:
                report.skipped = _unbound(connection)
                report.draft = _draft(connection)
                report.fits = self._approved_like(report.draft)
                continue
            try:
                template = self.store.catalog.approved(template_id)
            except CatalogError as exc:
                report.skipped = f"bound to {template_id}, which is not usable: {exc}"
                continue
            report.template = template_id
            ingested_by = earlier.get((connection.topic, connection.msgtype, template_id))
            if ingested_by not in (None, job.id):
                report.skipped = f"ingested from this bag into {template_id} by job {ingested_by}"
                report.ingested_by = ingested_by
                continue
            plans[connection.topic, connection.msgtype] = compile_plan(connection, template)
        _name_drafts_apart(reports)
        return reports, plans

    def _approved_like(self, draft: dict[str, Any] | None) -> list[str]:
        """The approved templates ``draft`` fits. A draft is meant to be a valid template
        (a type's name of 5,000 characters once drafted a description past the bound); one
        that is not anyway costs its topic this hint, never the job."""
        if draft is None:
            return []
        try:
            return self.store.catalog.approved_like(parse_template(draft))
        except TemplateInvalid:
            return []

    def _stage(self, job: Job) -> None:
        """Spool the bag's records; the job then commits them, none committed yet."""
        done = 0

        def progress(count: int) -> None:
            nonlocal done
            done += count
            # Not saved: staging restarts from the first message after a crash.
            self._update(job, save=False, messages_done=done)

        def plan(bag: Bag) -> Plans:
            reports, plans = self._plan(bag, job)
            total = _messages_in(bag, plans)
            self._update(
                job, status="staging", topics=reports, messages_total=total, messages_done=0
            )
            return plans

        if job.content is None:
            self._update(job, content=_content_of(job, _bag_in(self.root / job.id)))
        counts, parts = self._spool(job, plan, progress)
        self._update(
            job,
            status="committing",
            messages_done=done,
            records_staged=sum(counts.values()),
            staged=counts,
            spool_parts=parts,
            committed={template_id: 0 for template_id in counts},
        )

    def _restage(self, job: Job) -> None:
        """Spool the bag again for a job whose spool is lost: damaged by a power cut before a
        staging that did not sync it was saved as done, or removed with the bag of a job not
        resumed in time. It must give the records it gave the first time, past which the
        commit goes on, so it follows the job's plan, whatever was bound since. The job stays
        committing: a crash or failure here leaves it resumable, never counting its committed
        records as none."""
        counts, parts = self._spool(
            job, lambda bag: self._recorded_plans(bag, job), lambda count: None
        )
        if counts != job.staged:
            raise IngestFailed(
                "ingest_inconsistent",
                f"the bag's spool was lost and staging it again gave {counts} records, "
                f"not {job.staged}",
                {},
            )
        self._update(job, spool_parts=parts)

    def _recorded_plans(self, bag: Bag, job: Job) -> Plans:
        """The plans the job staged ``bag`` by, from its topics' reports."""
        connections = {(c.topic, c.msgtype): c for c in bag.connections}
        return {
            (report.topic, report.msgtype): compile_plan(
                connections[report.topic, report.msgtype],
                self.store.catalog.get(report.template).template,
            )
            for report in job.topics
            if report.template is not None and report.skipped is None
        }

    def _spool(
        self, job: Job, plan: Callable[[Bag], Plans], progress: Callable[[int], None]
    ) -> tuple[dict[str, int], int]:
        """Stage the bag into a new spool, synced, by the plans ``plan`` gives for it: its
        records per template, and its parts."""
        directory = self.root / job.id
        staged_dir = directory / "staged"
        shutil.rmtree(staged_dir, ignore_errors=True)
        self.disk_reserve.require_room()
        staged_dir.mkdir()
        robot = job.author["signer"]

        def progress_within_reserve(count: int) -> None:
            self.disk_reserve.require_room()
            progress(count)

        bag_path = _bag_in(directory)
        workers = StagingProcesses.start(
            bag_path,
            self.staging_workers,
            staged_dir,
            robot,
            self.store.arrays,
            self.worker_memory_bytes,
        )
        try:
            # The bag's files are checked while its messages stage.
            with bag_failures(bag_path), Bag.open(bag_path, check=False) as bag:
                plans = plan(bag)
                parts = (
                    workers.count if _messages_in(bag, plans) >= self.parallel_from_messages else 1
                )
                staged = workers.stage(
                    plans,
                    parts,
                    self.blobs(),
                    progress_within_reserve,
                    bag.check_files,
                    self.stall_s,
                )
                check_complete(bag, plans, staged)
        finally:
            workers.close()
        fsync_dir(staged_dir)
        return staged.records, parts

    def _commit(self, job: Job) -> None:
        author = Authorship(**job.author)
        if job.intent is not None:
            self._settle(job, author.meta())
        try:
            self._commit_spools(job, author)
        except SpoolDamaged as exc:
            log.warning("spool damaged, staging again", extra={"job": job.id, "error": str(exc)})
            self._restage(job)
            self._commit_spools(job, author)

    def _commit_spools(self, job: Job, author: Authorship) -> None:
        for template_id, staged in job.staged.items():
            if job.committed[template_id] >= staged:
                continue
            template = self.store.catalog.get(template_id).template
            spool = SpoolReader(self.root / job.id / "staged", template, job.spool_parts, staged)
            try:
                self._commit_spool(job, template_id, staged, spool, author)
            finally:
                spool.close()

    def _commit_spool(
        self, job: Job, template_id: str, staged: int, spool: SpoolReader, author: Authorship
    ) -> None:
        """Append a template's spooled records past those already committed, in batches."""
        spool.skip(job.committed[template_id])
        while job.committed[template_id] < staged:
            self.disk_reserve.require_room()
            start = job.committed[template_id]
            wanted = self.store.fitting(template_id, min(self.batch_records, staged - start))
            batch = spool.batch(wanted)
            count = len(batch.canonicals)
            if count != wanted:
                raise SpoolDamaged(f"{template_id}: the spool holds {start + count} of {staged}")
            intent = {
                "template": template_id,
                "start": start,
                "count": count,
                "log_size": self.logs.size(template_id),
            }
            self._update(job, intent=intent)
            first = self.store.append_prepared(template_id, batch, author=author)
            ids = record_id(template_id, first), record_id(template_id, first + count - 1)
            self._committed(job, template_id, start + count, *ids, save=False)

    def _committed(
        self, job: Job, template_id: str, upto: int, first: str, last: str, *, save: bool = True
    ) -> None:
        """Count a batch as committed. The count need not be saved at once (``save=False``):
        until the next save, job.json still holds the batch as its intent, which a restart
        settles against the log to the same count."""
        committed = {**job.committed, template_id: upto}
        span = job.record_ids.get(template_id, [first, last])
        self._update(
            job,
            save=save,
            committed=committed,
            records_committed=sum(committed.values()),
            record_ids={**job.record_ids, template_id: [span[0], last]},
            intent=None,
        )

    def _settle(self, job: Job, meta: bytes) -> None:
        """Decide whether the batch pending at the crash reached the log."""
        intent = job.intent
        assert intent is not None
        template_id = intent["template"]
        size = self.logs.size(template_id)
        found = [
            index
            for index in range(intent["log_size"], size)
            if self.logs.entry(template_id, index).meta == meta
        ]
        if found:
            if len(found) != intent["count"]:
                raise IngestFailed(
                    "ingest_inconsistent",
                    f"{template_id}: {len(found)} of a batch of {intent['count']} in the log",
                    {"template": template_id},
                )
            name, version = template_id.split("@")
            self._committed(
                job,
                template_id,
                intent["start"] + intent["count"],
                f"{name}-{version}-{found[0]}",
                f"{name}-{version}-{found[-1]}",
            )
        else:
            self._update(job, intent=None)
