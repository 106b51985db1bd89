"""Staging a bag: its bound messages into checked records, spooled per template.

Staging is pure Python for every message (rosbags' deserializer, conversion to the template,
the template's check, canonical bytes, the document its views keep), about 25 µs an IMU
message, and a bag holds hundreds of thousands of them: one interpreter is the bottleneck of an
ingest. So a large bag is cut into time windows, each staged by its own process
(:class:`StagingProcesses`) into its own spool part; a small one is staged by one of them.
Windows follow each other in time and the bag is read in time order, so the parts of a
template read in window order hold its records in exactly the order one pass would give, and
every message lies in exactly one window. The bag's index counts are checked over all windows
together.

The service never decodes a message itself: a message can decode to a hundred times its
bytes (a ROS 1 ``std_msgs/Bool[]`` is a Python object per byte, about 100 bytes each: 4 MB
took 411 MB and 5.8 s), and a chunk may hold 64 MiB. A staging process's address space is
bounded (:func:`~services.common.lifetime.limit_memory`), so such a message fails its job
(``message_too_large``) where it would have taken the service's memory.

Worker processes never talk to cas: a worker computes the CID of an image, a file or a large
array itself (the UnixFS import the SDK checks cas's answer against) and hands the bytes to
the parent, which stores them through the job's blob sink before any record is committed and
refuses the job if cas names them differently.
"""

from __future__ import annotations

import contextlib
import hashlib
import multiprocessing
import multiprocessing.forkserver
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from itertools import islice
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import IO, Any

import orjson

from robocloud.templates import (
    MAX_T,
    RecordInvalid,
    Template,
    check_envelope,
    parse_template,
    record_topic,
)
from robocloud.unixfs import import_bytes
from services.common.disk import ReserveReached
from services.common.errors import disk_full
from services.common.lifetime import die_with_parent, limit_memory
from services.storage.bags import (
    FALLBACK_STORES,
    Bag,
    BagConnection,
    BagCorrupt,
    BagError,
    MessageUndecodable,
    MissingDefinition,
    Window,
)
from services.storage.matcher import (
    BindingInvalid,
    BlobSink,
    ConversionError,
    Converter,
    compile_converter,
)
from services.storage.recordstore import ArrayOffload, Offload, OffloadFailed, SpooledRecords
from services.storage.segments import DocumentForm, PreparedDocuments

PROGRESS_EVERY = 1000
"""Messages between two progress reports, at most."""

PROGRESS_S = 2.0
"""Seconds between two progress reports, at most (checked after each message): a window of
slow messages still reports, so that silence means a stuck process (:data:`STALL_S`)."""

STALL_S = 120.0
"""A staging process that sends nothing for this long is stuck, and its job fails. One
message takes at most seconds: the costliest a staging process's memory allows (a 64 MiB
chunk of a ROS 1 ``std_msgs/Bool[]``, failing at 2 GiB) about 20."""

FREE_SPACE_HINT = "it may succeed once data is deleted or the service's operator frees space"

Plans = dict[tuple[str, str], tuple[Template, Converter]]
"""Per (topic, message type) bound to an approved template: the template and its converter."""


class IngestFailed(Exception):
    """An ingest job cannot go on: ``code`` and ``details`` are what the job reports."""

    def __init__(self, code: str, message: str, details: dict[str, Any]) -> None:
        super().__init__(message)
        self.code = code
        self.details = details


def job_failure(exc: BaseException) -> IngestFailed | None:
    """What a job that raised ``exc`` reports: ``exc`` itself when it is an
    ``IngestFailed``, ``insufficient_storage`` when it stopped at the disk's reserve or when it
    (or what it was raised from) says the disk is full, else None (a crash). The disk is named
    so that the robot learns the job failed for the service's disk, which lasts until space is
    freed, not for its bag; the reason names no path of the service's."""
    if isinstance(exc, IngestFailed):
        return exc
    if isinstance(exc, ReserveReached):
        return IngestFailed(
            "insufficient_storage",
            f"{exc}, so this job stopped; {FREE_SPACE_HINT}",
            {"free_bytes": exc.free_bytes, "reserve_bytes": exc.reserve_bytes},
        )
    full = disk_full(exc)
    if full is None:
        return None
    reason = full.strerror if isinstance(full, OSError) and full.strerror else str(full)
    return IngestFailed(
        "insufficient_storage",
        f"the service's disk is full ({reason}), so this job failed; {FREE_SPACE_HINT}",
        {},
    )


class SpoolDamaged(Exception):
    """A spool holds other than the records its job staged: what a power cut leaves of one
    whose tail had not reached the disk. Its records are read again from the bag."""


@dataclass
class Staged:
    """What staging one window (or the whole bag) spooled."""

    records: dict[str, int] = field(default_factory=dict)
    """Records per template id."""
    messages: dict[tuple[str, str], int] = field(default_factory=dict)
    """Messages read per (topic, message type)."""

    def add(self, other: Staged) -> None:
        for template_id, count in other.records.items():
            self.records[template_id] = self.records.get(template_id, 0) + count
        for key, count in other.messages.items():
            self.messages[key] = self.messages.get(key, 0) + count


SPOOL_FORMAT = 2
"""In a spool's names: a spool of another format (staged before an upgrade, by a job resumed
after it) is missing to this one, which stages the bag again rather than misread its lines.
2: a template whose strings are all inside arrays has a keyword text line."""


def spool_path(directory: Path, template_id: str, part: int, kind: str = "lines") -> Path:
    """One of a spool part's two files: ``lines`` holds, for each record, its canonical bytes,
    its document as :class:`DocumentForm` prepares it and, for a template with strings, its
    keyword text (a JSON string), a line each; ``rows`` its indexed values, fixed width."""
    return directory / f"{template_id}.{part}.{kind}.v{SPOOL_FORMAT}"


class SpoolWriter:
    """A template's spool part: each staged record with what its views will keep of it, so
    that the commit writes segments without parsing a record."""

    def __init__(self, directory: Path, template: Template, part: int) -> None:
        self.form = DocumentForm(template)
        self._lines = spool_path(directory, template.id, part).open("wb")
        self._rows = spool_path(directory, template.id, part, "rows").open("wb")

    def write(self, canonical: bytes) -> None:
        doc, row, text = self.form.prepared(canonical)
        if text is None:
            self._lines.write(b"%s\n%s\n" % (canonical, doc))
        else:
            self._lines.write(b"%s\n%s\n%s\n" % (canonical, doc, orjson.dumps(text)))
        self._rows.write(row)

    def sync(self) -> None:
        """Put the part on the disk: once the job saves it as staged, a power cut must not
        take records from it (the directory's entry is the job's to sync)."""
        for file in (self._lines, self._rows):
            file.flush()
            os.fdatasync(file.fileno())

    def close(self) -> None:
        self._lines.close()
        self._rows.close()


class SpoolReader:
    """A template's spool, part after part: its records in the bag's order, in batches read
    whole (a batch's lines in one C loop, its rows in one read).

    A damaged spool raises :class:`SpoolDamaged` before a batch holding a record out of place
    is returned: its rows must hold ``records`` in all, and each part as many lines as rows
    (checked at the part's end), so that no part is short while a later one is read.
    """

    def __init__(self, directory: Path, template: Template, parts: int, records: int) -> None:
        self.form = DocumentForm(template)
        self._lines_per_record = 3 if self.form.text_of else 2
        self._paths = [
            (
                spool_path(directory, template.id, part),
                spool_path(directory, template.id, part, "rows"),
            )
            for part in range(parts)
        ]
        self._part: tuple[IO[bytes], IO[bytes]] | None = None
        size = sum(path.stat().st_size for _, path in self._paths if path.exists())
        if size != records * self.form.row.size:
            raise SpoolDamaged(
                f"{template.id}: the spool's rows are {size} bytes, not those of {records} records"
            )

    def _take(self, count: int) -> tuple[list[bytes], bytes]:
        """The lines and the rows of the next ``count`` records (fewer at the spool's end)."""
        lines: list[bytes] = []
        rows: list[bytes] = []
        per_record, row_size = self._lines_per_record, self.form.row.size
        while count and (self._part is not None or self._open_next()):
            assert self._part is not None
            text, table = self._part
            taken = list(islice(text, count * per_record))
            records = len(taken) // per_record
            row_bytes = table.read(records * row_size)
            torn = bool(taken) and not taken[-1].endswith(b"\n")
            if torn or len(taken) % per_record or len(row_bytes) != records * row_size:
                raise SpoolDamaged(f"{text.name}: its lines and rows do not hold the same records")
            lines += taken
            rows.append(row_bytes)
            count -= records
            if count:
                self._end_part()
        return lines, b"".join(rows)

    def _end_part(self) -> None:
        """Close the part whose lines are all read, once its rows are too."""
        assert self._part is not None
        text, table = self._part
        if table.read(1):
            raise SpoolDamaged(f"{text.name}: it holds fewer lines than rows")
        self._close_part()

    def _open_next(self) -> bool:
        while self._paths:
            lines_path, rows_path = self._paths.pop(0)
            present = lines_path.exists(), rows_path.exists()
            if any(present):  # a window without the template's records spools nothing
                if not all(present):
                    raise SpoolDamaged(f"{lines_path.name}: its lines or its rows are missing")
                self._part = (lines_path.open("rb"), rows_path.open("rb"))
                return True
        return False

    def _close_part(self) -> None:
        if self._part is not None:
            for file in self._part:
                file.close()
            self._part = None

    def skip(self, count: int) -> None:
        while count:
            taken = len(self._take(min(count, 65_536))[0]) // self._lines_per_record
            if not taken:
                return
            count -= taken

    def batch(self, count: int) -> SpooledRecords:
        """The next ``count`` records (fewer at the spool's end)."""
        lines, rows = self._take(count)
        per_record = self._lines_per_record
        documents = PreparedDocuments(lines[1::per_record], rows, self.form.row.size)
        texts = lines[2::per_record] if per_record == 3 else None
        return SpooledRecords([line[:-1] for line in lines[::per_record]], documents, texts)

    def close(self) -> None:
        self._close_part()
        self._paths.clear()


def compile_plan(connection: BagConnection, template: Template) -> tuple[Template, Converter]:
    """The converter filling ``template`` from ``connection``'s messages, or the job's error."""
    if connection.typestore is None:
        raise IngestFailed(
            "message_type_undefined",
            f"topic {connection.topic!r} is bound to {template.id} but its type "
            f"cannot be decoded: {connection.problem}",
            {"topic": connection.topic, "msgtype": connection.msgtype},
        )
    try:
        return template, compile_converter(template, connection.typestore, connection.msgtype)
    except BindingInvalid as exc:
        raise IngestFailed(
            "binding_invalid",
            str(exc),
            {"topic": connection.topic, "template": template.id, "field": exc.path},
        ) from exc


@contextmanager
def bag_failures(bag: Path) -> Iterator[None]:
    """What reading or decoding ``bag`` raises, as the job's error."""
    try:
        yield
    except BagError as exc:
        raise IngestFailed(
            "bag_corrupt" if isinstance(exc, BagCorrupt) else "bag_unreadable",
            exc.shown(bag),
            {"file": exc.file_in(bag), "offset": exc.offset},
        ) from exc
    except MissingDefinition as exc:
        raise IngestFailed(
            "message_type_undefined", str(exc), {"topic": exc.topic, "msgtype": exc.msgtype}
        ) from exc
    except MessageUndecodable as exc:
        raise IngestFailed(
            "message_undecodable", str(exc), {"topic": exc.topic, "t": exc.t_ns}
        ) from exc


@dataclass(frozen=True)
class RecordMaker:
    """A bound connection's messages as checked records of its template."""

    template: Template
    converter: Converter
    topic: str
    robot: str
    arrays: ArrayOffload
    blobs: BlobSink

    def envelope(self, t_ns: int) -> dict[str, Any]:
        """A record without data; its envelope is checked once per connection, since only
        ``t`` changes from one message to the next."""
        return {
            "template": self.template.id,
            "topic": record_topic(self.topic),
            "robot": self.robot,
            "t": t_ns,
            "data": None,
        }

    def check(self) -> None:
        try:
            check_envelope(self.envelope(0))
        except RecordInvalid as exc:
            raise self._invalid(0, exc) from exc

    def encoded(self, message: Any, t_ns: int) -> bytes:
        """The canonical bytes of one message's record, as its log will hold them."""
        try:
            t = self.converter.record_time(message, t_ns)
            if not 0 <= t <= MAX_T:
                raise RecordInvalid("t", "must be an integer of nanoseconds from 0 to 2**63 - 1")
            record = self.envelope(t)
            record["data"] = self.converter.data(message, self.blobs)
            canonical = self.template.encoder.canonical_enveloped(record)
            return self.arrays.encoded(self.template, record, canonical).canonical
        except (ConversionError, RecordInvalid) as exc:
            raise self._invalid(t_ns, exc) from exc
        except OffloadFailed as exc:
            raise IngestFailed(
                "cas_unavailable",
                f"topic {self.topic!r} at t={t_ns}: {exc}",
                {"topic": self.topic, "t": t_ns, "field": exc.path, "template": self.template.id},
            ) from exc

    def _invalid(self, t_ns: int, exc: ConversionError | RecordInvalid) -> IngestFailed:
        return IngestFailed(
            "record_invalid",
            f"topic {self.topic!r} at t={t_ns}: {exc.path}: {exc.reason}",
            {"topic": self.topic, "t": t_ns, "field": exc.path, "template": self.template.id},
        )


def stage_window(
    bag: Bag,
    plans: Plans,
    window: Window,
    directory: Path,
    part: int,
    robot: str,
    arrays: ArrayOffload,
    blobs: BlobSink,
    progress: Callable[[int], None],
) -> Staged:
    """Spool the records of ``window``'s messages to part ``part`` of each template's spool
    under ``directory`` (the caller checks the counts over all windows)."""
    makers_by_key = {
        (topic, msgtype): RecordMaker(template, converter, topic, robot, arrays, blobs)
        for (topic, msgtype), (template, converter) in plans.items()
    }
    for each in makers_by_key.values():
        each.check()
    spools: dict[str, SpoolWriter] = {}
    staged = Staged()
    records, messages = staged.records, staged.messages
    unreported, reported_at = 0, time.monotonic()
    try:
        for connection, t_ns, raw in bag.raw_messages({topic for topic, _ in plans}, window):
            key = (connection.topic, connection.msgtype)
            maker = makers_by_key.get(key)
            if maker is None:
                continue
            canonical = _record_bytes(bag, maker, connection, t_ns, raw)
            template_id = maker.template.id
            spool = spools.get(template_id)
            if spool is None:
                spool = spools[template_id] = SpoolWriter(directory, maker.template, part)
            spool.write(canonical)
            records[template_id] = records.get(template_id, 0) + 1
            messages[key] = messages.get(key, 0) + 1
            unreported += 1
            if unreported == PROGRESS_EVERY or time.monotonic() - reported_at >= PROGRESS_S:
                progress(unreported)
                unreported, reported_at = 0, time.monotonic()
        for spool in spools.values():
            spool.sync()
    finally:
        for spool in spools.values():
            spool.close()
    progress(unreported)
    return staged


def _record_bytes(
    bag: Bag, maker: RecordMaker, connection: BagConnection, t_ns: int, raw: bytes
) -> bytes:
    """One message's record; a message decoding past this process's memory fails the job
    once what it decoded is freed. The :class:`MemoryError`'s traceback holds the decoder's
    frames, and with them the objects it made: a failure raised while handling it had no
    memory left to be reported with, and the process spun on failed allocations."""
    try:
        return maker.encoded(bag.deserialize(connection, t_ns, raw), t_ns)
    except MemoryError:
        pass
    raise _too_large(connection.topic, t_ns, len(raw))


def _too_large(topic: str, t_ns: int, size: int) -> IngestFailed:
    return IngestFailed(
        "message_too_large",
        f"topic {topic!r} at t={t_ns}: its {size}-byte message decodes to more than a staging "
        "process may hold (ROBOCLOUD_STORAGE_INGEST_WORKER_MEMORY_BYTES)",
        {"topic": topic, "t": t_ns, "bytes": size},
    )


# ----- staging in worker processes -----
@dataclass(frozen=True)
class WindowTask:
    """What a worker process needs to stage one window (sent to it pickled); the templates
    follow once the job has planned (see :class:`StagingProcesses`)."""

    bag: Path
    directory: Path
    part: int
    """The window this process stages, once the plan tells into how many the bag is cut."""
    robot: str
    inline_bytes: int
    offload: bool
    """Whether large arrays may go to cas (False: this node has none, the job fails)."""
    memory_bytes: int
    """The process's address space (0: unbounded)."""


BLOB_BATCH_COUNT = 256
"""Blobs stored in one exchange with cas, at most: a laser scan's arrays are a blob or two a
message, and one signed ``add`` each (5 ms) cost more than staging the messages did."""
BLOB_BATCH_BYTES = 4 * 1024 * 1024
"""Bytes of blobs the service holds before it stores them (a blob larger goes alone)."""


class CasBlobs:
    """Image and file bytes into cas, each distinct content uploaded once per job.

    Camera streams repeat frames (and calibration blobs repeat always); content addressing
    makes the CID of bytes seen before known without asking cas again.
    """

    def __init__(self, add: Offload, remembered: int = 4096) -> None:
        self._add = add
        self._remembered = remembered
        self._known: OrderedDict[bytes, str] = OrderedDict()

    def put(self, data: bytes) -> str:
        (cid,) = self.put_many([data])
        return cid

    def put_many(self, blobs: Sequence[bytes]) -> list[str]:
        """Their CIDs, in order; the contents not known yet added in one call of ``add``."""
        keys = [hashlib.sha256(data).digest() for data in blobs]
        cids = {key: self._known[key] for key in keys if key in self._known}
        new = {key: data for key, data in zip(keys, blobs, strict=True) if key not in cids}
        if new:
            for key, cid in zip(new, self._add(list(new.values())), strict=True):
                cids[key] = cid
                self._known[key] = cid
                if len(self._known) > self._remembered:
                    self._known.popitem(last=False)
        return [cids[key] for key in keys]


def _forwarded(parent: Connection) -> Offload:
    """A worker's way to cas: the CIDs computed here, the bytes sent to the parent."""

    def add(blobs: Sequence[bytes]) -> list[str]:
        cids = []
        for data in blobs:
            cid = str(import_bytes(data)[1])
            parent.send(("blob", cid, data))
            cids.append(cid)
        return cids

    return add


def _release_forkserver() -> None:
    """Close this process's copy of the service's end of the forkserver's pipe, whose end
    the forkserver waits for to exit with the service. multiprocessing hands a copy to every
    process the forkserver forks (for processes of their own, which staging never starts),
    so a staging process kept the forkserver, its parent, alive after the service died, and
    its parent-death signal never came (tested: it ran on). Called after
    :func:`die_with_parent`: the forkserver cannot end before the signal is armed."""
    server = multiprocessing.forkserver._forkserver
    alive = getattr(server, "_forkserver_alive_fd", None)
    if alive is not None:
        with contextlib.suppress(OSError):
            os.close(alive)
        server._forkserver_alive_fd = None  # type: ignore[attr-defined]


def _stage_task(task: WindowTask, parent: Connection) -> None:
    """A worker process's body: every outcome is one message to the parent.

    It dies with the service: a worker decoding a bag's messages writes to the service only
    between messages (:data:`PROGRESS_EVERY`, :data:`PROGRESS_S`), so one stuck in a slow
    message ran on after a ``kill -9`` of the service. Its parent is the forkserver, which
    ends when the service does once no worker holds the pipe it waits on
    (:func:`_release_forkserver`), and the kernel then kills the worker
    (:func:`die_with_parent`).
    """
    die_with_parent()
    _release_forkserver()
    limit_memory(task.memory_bytes)
    try:
        # The job's own open checks the bag; it sends no plan unless the bag passed.
        with bag_failures(task.bag), Bag.open(task.bag, check=False) as bag:
            order = parent.recv()
            if order[0] != "plan":
                return
            _, documents, windows = order
            window = bag.time_windows(windows)[task.part]
            connections = {(c.topic, c.msgtype): c for c in bag.connections}
            plans = {
                key: compile_plan(connections[key], parse_template(document))
                for key, document in documents.items()
            }
            blobs = CasBlobs(_forwarded(parent))
            arrays = ArrayOffload(task.inline_bytes, blobs.put_many if task.offload else None)

            def progress(count: int) -> None:
                parent.send(("progress", count))

            staged = stage_window(
                bag,
                plans,
                window,
                task.directory,
                task.part,
                task.robot,
                arrays,
                blobs,
                progress,
            )
        parent.send(("done", staged))
    except Exception as exc:
        failure = job_failure(exc)
        if failure is None:
            parent.send(("crashed", f"{type(exc).__name__}: {exc}"))
        else:
            parent.send(("failed", failure.code, str(failure), failure.details))


PRELOADED = [__name__, *(f"rosbags.typesys.stores.{store.value}" for store in FALLBACK_STORES)]
"""What the server that workers fork from loads before the first: this module, and rosbags'
typestores for bags without definitions, whose import (0.17 s for ROS 1's) each worker paid
again, doubling the ingest of a bag of 500 messages."""


def _context() -> Any:
    """Workers fork from a clean server process with :data:`PRELOADED` loaded: never from the
    storage service itself, whose other threads may hold locks at the moment of a fork.
    (A worker imports the main module of a program run as a script, as any spawned process
    does; the service runs as ``python -m``, whose main it skips.)"""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOADED)
    return context


def start_workers_server(*, wait: bool = False) -> None:
    """Start the server that staging processes fork from, if it is not running: with the
    service, so that it has loaded its modules (about half a second) before a job needs it.
    With ``wait``, return once it has (a process that does nothing started and ended)."""
    context = _context()
    multiprocessing.forkserver.ensure_running()
    if wait:
        process = context.Process(target=int, name="stage-warm-up")
        process.start()
        process.join()


class BlobBatches:
    """The blobs staging processes send, whose CIDs they computed, stored a batch at a time
    (:data:`BLOB_BATCH_COUNT`, :data:`BLOB_BATCH_BYTES`); :meth:`flush` stores the rest. A
    job's records are committed after its staging, so every blob is in cas before a record
    that names it."""

    def __init__(self, store: Offload) -> None:
        self._store = store
        self._cids: list[str] = []
        self._blobs: list[bytes] = []
        self._bytes = 0

    def add(self, cid: str, data: bytes) -> None:
        self._cids.append(cid)
        self._blobs.append(data)
        self._bytes += len(data)
        if len(self._blobs) >= BLOB_BATCH_COUNT or self._bytes >= BLOB_BATCH_BYTES:
            self.flush()

    def flush(self) -> None:
        """Store what is held; ``cas_unavailable`` when cas fails or names a blob wrongly."""
        cids, blobs = self._cids, self._blobs
        if not blobs:
            return
        self._cids, self._blobs, self._bytes = [], [], 0
        try:
            stored = self._store(blobs)
        except Exception as exc:
            size = sum(len(data) for data in blobs)
            raise IngestFailed(
                "cas_unavailable",
                f"storing {len(blobs)} blobs ({size} bytes; {cids[0]} first) in cas failed: {exc}",
                {},
            ) from exc
        for cid, data, answer in zip(cids, blobs, stored, strict=True):
            if answer != cid:
                raise IngestFailed(
                    "cas_unavailable",
                    f"cas stored {len(data)} bytes as {answer} where their CID is {cid}",
                    {"cid": cid},
                )


class StagingProcesses:
    """Processes that stage a bag's windows, started before the job has read the bag: each
    reads the bag's index (a quarter of a second for 200,000 ROS 1 messages) while the job
    reads it to plan, then waits for the plan (:meth:`stage`), or is stopped (:meth:`close`)
    when the bag is cut into fewer windows than there are processes.
    """

    def __init__(self, tasks: list[WindowTask]) -> None:
        context = _context()
        self.count = len(tasks)
        self._workers: list[tuple[Any, Connection]] = []
        try:
            for task in tasks:
                here, there = context.Pipe()
                process = context.Process(
                    target=_stage_task, args=(task, there), name=f"stage-{task.part}", daemon=True
                )
                process.start()
                there.close()
                self._workers.append((process, here))
        except BaseException:
            self.close()
            raise

    @classmethod
    def start(
        cls,
        bag: Path,
        count: int,
        directory: Path,
        robot: str,
        arrays: ArrayOffload,
        memory_bytes: int,
    ) -> StagingProcesses:
        offload = arrays.offload is not None
        return cls(
            [
                WindowTask(bag, directory, part, robot, arrays.inline_bytes, offload, memory_bytes)
                for part in range(count)
            ]
        )

    def stage(
        self,
        plans: Plans,
        windows: int,
        blobs: Offload,
        progress: Callable[[int], None],
        alongside: Callable[[], None],
        stall_s: float = STALL_S,
    ) -> Staged:
        """Stage the bag cut into ``windows`` (at most :attr:`count`) with ``plans`` while
        ``alongside`` (the check of the bag's files) runs here; the first failure of either
        stops them all, as does a process that sends nothing for ``stall_s``. The processes
        past ``windows`` are told to end."""
        templates = {key: template.to_json() for key, (template, _) in plans.items()}
        for part, (_, worker) in enumerate(self._workers):
            try:
                worker.send(("plan", templates, windows) if part < windows else ("end",))
            except OSError:
                continue  # it failed reading the bag: its message says why
        check = _Alongside(alongside)
        staged = Staged()
        batches = BlobBatches(blobs)
        pending = {worker: part for part, (_, worker) in enumerate(self._workers[:windows])}
        heard = dict.fromkeys(pending, time.monotonic())
        try:
            while pending or not check.done():
                check.raise_failure()
                for ready in wait(list(pending), timeout=0.05):
                    assert isinstance(ready, Connection)
                    heard[ready] = time.monotonic()
                    if _handle(ready, pending[ready], batches, progress, staged):
                        del pending[ready]
                _raise_stalled(pending, heard, stall_s)
            batches.flush()
        except IngestFailed:
            check.join()  # a worker reading a damaged bag fails in its own words: the check's win
            check.raise_failure()
            raise
        check.raise_failure()
        return staged

    def close(self) -> None:
        """Stop what is still running (after a failure)."""
        for process, worker in self._workers:
            if process.is_alive():
                process.terminate()
            process.join()
            worker.close()


class _Alongside:
    """A function run on its own thread; its exception raised where :meth:`raise_failure`
    is called."""

    def __init__(self, run: Callable[[], None]) -> None:
        self._failure: BaseException | None = None
        self._run = run
        self._thread = threading.Thread(target=self._main, name="stage-check", daemon=True)
        self._thread.start()

    def _main(self) -> None:
        try:
            self._run()
        except BaseException as exc:
            self._failure = exc

    def done(self) -> bool:
        return not self._thread.is_alive()

    def join(self) -> None:
        self._thread.join()

    def raise_failure(self) -> None:
        if self._failure is not None:
            raise self._failure


def _raise_stalled(
    pending: Mapping[Connection, int], heard: Mapping[Connection, float], stall_s: float
) -> None:
    now = time.monotonic()
    for worker, part in pending.items():
        if now - heard[worker] > stall_s:
            raise IngestFailed(
                "ingest_stalled",
                f"staging process {part} sent nothing for {stall_s:g} s: a message it stages "
                "takes longer than any should (ROBOCLOUD_STORAGE_INGEST_STALL_S)",
                {"part": part},
            )


def _handle(
    worker: Connection,
    part: int,
    blobs: BlobBatches,
    progress: Callable[[int], None],
    staged: Staged,
) -> bool:
    """Act on one message of a worker; True once it has finished its window."""
    try:
        message = worker.recv()
    except (EOFError, OSError):  # it ended, or ended mid-message (connection reset)
        raise IngestFailed(
            "ingest_failed", f"staging process {part} ended without a result", {"part": part}
        ) from None
    kind = message[0]
    if kind == "progress":
        progress(message[1])
    elif kind == "blob":
        blobs.add(message[1], message[2])
    elif kind == "done":
        staged.add(message[1])
        return True
    elif kind == "failed":
        raise IngestFailed(message[1], message[2], message[3])
    else:
        raise IngestFailed("ingest_failed", f"staging process {part}: {message[1]}", {})
    return False


def check_complete(bag: Bag, plans: Mapping[tuple[str, str], Any], staged: Staged) -> None:
    """Every bound connection's messages were read, as many as the bag's index counts."""
    bag.check_counts({key: staged.messages.get(key, 0) for key in plans})
