"""The knowledge base: validated descriptions, indexed for SPARQL, fed by robots and the ledger.

A description arrives as a CID, by ``POST /v1/knowledge`` or advertised on the ledger
(``Registry.advertise(cid, descriptionCid)``). It is fetched from cas (verified against its CID
by the SDK), read in canonical form, checked against the SHACL shapes, and written to
``knowledge/descriptions/<cid>.nt`` before it is acknowledged: those files are the truth.
The SPARQL workers (``services.storage.sparql``) build their graphs from them, so a restart or
a kill -9 re-reads local files and fetches nothing again.

The ledger follower keeps its place in ``knowledge/follow.json`` (the last advertisement
handled, descriptions whose fetch failed and are retried with a backoff, and those refused,
with why). When
the directory is lost, it starts again from block 0 and fetches every advertised description
from cas again: the knowledge base rebuilds itself from cas and the chain.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from robocloud.cas import ContentTooLargeError
from robocloud.cid import CID, parse_cid
from robocloud.errors import NotFoundError, RobocloudError
from robocloud.ledger.models import Role
from robocloud.semantic import (
    MAX_DESCRIPTION_BYTES,
    MAX_DESCRIPTION_TRIPLES,
    MEDIA_TYPES,
    Description,
    DescriptionInvalidError,
    DescriptionSyntaxError,
    DescriptionTooLargeError,
    NotADescriptionError,
    SemanticError,
    parse_canonical,
    validate,
)
from robocloud.unixfs import import_bytes
from services.common.durable import AppendLog, atomic_write
from services.storage.sparql import SparqlWorkers

log = logging.getLogger("robocloud.storage.knowledge")

MAX_PENDING = 10_000
"""Advertised descriptions whose fetch failed, kept for retry; the oldest go beyond this."""
MAX_REFUSED = 100_000
MAX_ATTEMPTS = 16
"""Failed fetches of an advertised description before it is refused for good: anyone may
advertise a CID that cas never holds, and each one kept would be fetched again for ever."""
MAX_BACKOFF_S = 3600.0
"""The longest wait between two fetches of one pending description (the first waits one poll
interval, each later one twice the one before): 16 attempts span several hours."""
MAX_RETRIES_PER_ROUND = 50
"""Pending descriptions fetched again in one poll, so that retries cannot delay new ones."""


class KnowledgeError(Exception):
    """Base of the knowledge base's domain errors; ``cid`` names the description."""

    def __init__(self, message: str, cid: str) -> None:
        super().__init__(message)
        self.cid = cid


class DescriptionNotFound(KnowledgeError):
    """cas does not have the description."""


class CasUnavailable(KnowledgeError):
    """cas could not be asked (down, or answered something that is not the content)."""


class DescriptionRefused(KnowledgeError):
    """The bytes at the CID are not a valid description (``reason`` is the SDK's error)."""

    def __init__(self, cid: str, reason: SemanticError) -> None:
        super().__init__(f"{cid}: {reason}", cid)
        self.reason = reason


class DescriptionInvalid(DescriptionRefused):
    """It fails its shapes; ``violations`` lists each one."""

    @property
    def violations(self) -> list[dict[str, str | None]]:
        assert isinstance(self.reason, DescriptionInvalidError)
        return [violation.as_dict() for violation in self.reason.violations]


class DescriptionUnparsable(DescriptionRefused):
    """It is not RDF (``line`` where known)."""

    @property
    def line(self) -> int | None:
        return getattr(self.reason, "line", None)


class NotADescription(DescriptionRefused):
    """RDF or bytes that are not a robocloud description."""


class CidNotCanonical(DescriptionRefused):
    """The bytes are sent under another CID than the one they have in canonical form.

    A description is named by the CID of its canonical bytes as ``robocloud.unixfs`` imports
    them (CIDv1, raw leaves: what cas answers when they are added), and the SPARQL workers
    load a stored file only if its bytes have its name. The same bytes under a CIDv0 or a
    dag-pb CID were acknowledged once and then never loaded; ``expected`` is the CID to use.
    """

    def __init__(self, cid: str, expected: str) -> None:
        super().__init__(
            cid,
            NotADescriptionError(
                f"a description is added by the CID of its canonical bytes, {expected}"
            ),
        )
        self.expected = expected


class DescriptionTooLarge(DescriptionRefused):
    """More bytes or triples than a description may hold."""

    @property
    def limit(self) -> int:
        assert isinstance(self.reason, DescriptionTooLargeError)
        return self.reason.limit


class KnowledgeBaseFull(KnowledgeError):
    """The description would take the knowledge base past its total size: every SPARQL
    worker holds the whole graph, and one that cannot load it dies at start, again and again,
    leaving no query answered. Not the description's fault: the ledger follower tries it again
    later, as after a failed fetch."""

    def __init__(self, cid: str, size: int, used: int, limit: int) -> None:
        super().__init__(
            f"the knowledge base holds {used} bytes of descriptions; {cid} ({size} bytes) "
            f"would take it past its {limit} (ROBOCLOUD_KNOWLEDGE_MAX_TOTAL_BYTES)",
            cid,
        )
        self.size = size
        self.used = used
        self.limit = limit


class ShareExhausted(KnowledgeError):
    """The description would take the robot that adds it (its signer, or its advertiser on the
    ledger) past its share of the knowledge base: without one, a single robot could fill the
    whole of it, and every other robot's descriptions were refused."""

    def __init__(self, cid: str, robot: str, size: int, used: int, limit: int) -> None:
        super().__init__(
            f"{robot} holds {used} bytes of descriptions; {cid} ({size} bytes) would take it "
            f"past its share of {limit} (ROBOCLOUD_KNOWLEDGE_MAX_BYTES_PER_ROBOT)",
            cid,
        )
        self.robot = robot
        self.size = size
        self.used = used
        self.limit = limit


def _refused(cid: str, reason: SemanticError) -> DescriptionRefused:
    kinds: list[tuple[type[SemanticError], type[DescriptionRefused]]] = [
        (DescriptionInvalidError, DescriptionInvalid),
        (DescriptionSyntaxError, DescriptionUnparsable),
        (DescriptionTooLargeError, DescriptionTooLarge),
    ]
    for reason_type, refusal in kinds:
        if isinstance(reason, reason_type):
            return refusal(cid, reason)
    return NotADescription(cid, reason)


class InvalidTypeParameter(ValueError):
    def __init__(self, field: str, value: str) -> None:
        super().__init__(
            f"{field} must be a media type (image/jpeg), an IANA media type IRI or a "
            f"template's ipfs://<cid>, not {value[:200]!r}"
        )
        self.field = field
        self.value = value


class CasReader(Protocol):
    def get(self, cid: CID | str, *, max_size: int | None = None) -> bytes: ...


class Advertisement(Protocol):
    block_number: int
    log_index: int
    advertiser: str
    description: str | None


class LedgerReader(Protocol):
    def advertisements(
        self, *, since: int, after_log_index: int | None, limit: int, wait_s: float
    ) -> list[Any]: ...

    def robot(self, address: str) -> Any: ...


Connect = Callable[[], AbstractContextManager[CasReader]]
ConnectLedger = Callable[[], AbstractContextManager[LedgerReader]]


@dataclass(frozen=True)
class Indexed:
    """What ``add`` did: the description's CID, what it describes, and whether it was new."""

    cid: str
    subjects: dict[str, str]
    triples: int
    new: bool

    def as_dict(self) -> dict[str, Any]:
        return {
            "cid": self.cid,
            "subjects": self.subjects,
            "triples": self.triples,
            "new": self.new,
        }


@dataclass(frozen=True)
class Retry:
    """A pending description's failed fetches so far, when (epoch seconds) to fetch it again,
    and who is charged for it once it is indexed: its advertiser, or None for a storage
    node's (and in files saved before)."""

    attempts: int
    due: float
    robot: str | None = None


@dataclass
class FollowState:
    """Where the ledger follower is, persisted in ``follow.json``.

    ``retries`` holds the backoff of pending descriptions; a pending CID without one (a file
    written before retries were saved) is due at once, with no attempt counted.
    """

    block: int = 0
    log_index: int = -1
    pending: list[str] | None = None
    refused: dict[str, str] | None = None
    retries: dict[str, Retry] = field(default_factory=dict)

    @classmethod
    def load(cls, path: Path) -> FollowState:
        """The saved state; a missing or unreadable file starts over from block 0 (the
        descriptions already on disk are not fetched again, only re-checked as seen)."""
        try:
            document = json.loads(path.read_text())
            return cls(
                int(document["block"]),
                int(document["log_index"]),
                [str(cid) for cid in document["pending"]],
                {str(cid): str(why) for cid, why in document["refused"].items()},
                {
                    str(cid): Retry(
                        int(retry["attempts"]),
                        float(retry["due"]),
                        None if retry.get("robot") is None else str(retry["robot"]),
                    )
                    for cid, retry in document.get("retries", {}).items()
                },
            )
        except FileNotFoundError:
            return cls(0, -1, [], {})
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            log.warning("%s is unreadable (%s): following the ledger from block 0", path, exc)
            return cls(0, -1, [], {})

    def save(self, path: Path) -> None:
        document = {
            "block": self.block,
            "log_index": self.log_index,
            "pending": self.pending or [],
            "refused": self.refused or {},
            "retries": {
                cid: {"attempts": retry.attempts, "due": retry.due, "robot": retry.robot}
                for cid, retry in self.retries.items()
            },
        }
        atomic_write(path, json.dumps(document, sort_keys=True).encode())


class KnowledgeBase:
    """Descriptions on disk, SPARQL workers over them, and the ledger follower."""

    def __init__(
        self,
        root: Path,
        workers: SparqlWorkers,
        connect_cas: Connect,
        *,
        max_bytes: int = MAX_DESCRIPTION_BYTES,
        max_triples: int = MAX_DESCRIPTION_TRIPLES,
        max_total_bytes: int | None = None,
        max_bytes_per_robot: int | None = None,
    ) -> None:
        self.root = root
        self.descriptions = root / "descriptions"
        self.descriptions.mkdir(parents=True, exist_ok=True)
        self.workers = workers
        self.connect_cas = connect_cas
        self.max_bytes = max_bytes
        self.max_triples = max_triples
        self.max_total_bytes = max_total_bytes
        self.max_bytes_per_robot = max_bytes_per_robot
        self._lock = threading.Lock()
        sizes = {path.stem: path.stat().st_size for path in self.descriptions.glob("*.nt")}
        self._known = set(sizes)
        self.total_bytes = sum(sizes.values())
        """The canonical N-Triples of every description: what each worker's graph is built
        from, and what ``max_total_bytes`` bounds."""
        self._owners = AppendLog(root / "owners.log")
        self._robot_bytes = self._read_owners(sizes)
        """What each robot's descriptions take, for ``max_bytes_per_robot``."""
        self._follower: LedgerFollower | None = None

    def __len__(self) -> int:
        with self._lock:
            return len(self._known)

    def __contains__(self, cid: str) -> bool:
        with self._lock:
            return cid in self._known

    def add(
        self, cid_text: str, cas: CasReader | None = None, *, robot: str | None = None
    ) -> Indexed:
        """Fetch, read, validate and store the description at ``cid_text``; idempotent.

        ``cas`` is a client to fetch it with (the follower's, shared by one round); without
        one, a client is opened for this description. ``robot`` (the signer, or the
        advertiser) is charged for a new description; None charges no one (the node's own
        dataset descriptions). Raises :class:`CidNotCanonical` when the bytes there have
        another canonical CID.
        """
        cid = str(parse_cid(cid_text, "cid").to_v1())
        description = self._fetch(cid, cid_text, cas)
        new = self._store(cid, description, robot)
        return Indexed(cid, description.subjects(), len(description), new)

    def _fetch(self, cid: str, cid_text: str, client: CasReader | None) -> Description:
        try:
            with nullcontext(client) if client is not None else self.connect_cas() as cas:
                data = cas.get(cid, max_size=self.max_bytes)
        except ContentTooLargeError as exc:
            size = exc.declared or self.max_bytes + 1
            raise DescriptionTooLarge(
                cid, DescriptionTooLargeError("bytes", size, self.max_bytes)
            ) from None
        except NotFoundError:
            raise DescriptionNotFound(f"cas does not have {cid}", cid) from None
        except RobocloudError as exc:
            raise CasUnavailable(f"cannot fetch {cid} from cas: {exc}", cid) from None
        expected = str(import_bytes(data)[1])
        if expected != cid:
            raise CidNotCanonical(cid_text, expected)
        try:
            description = parse_canonical(
                data, max_bytes=self.max_bytes, max_triples=self.max_triples
            )
            return validate(description)
        except SemanticError as exc:
            raise _refused(cid, exc) from None

    def _read_owners(self, sizes: dict[str, int]) -> dict[str, int]:
        """Each robot's bytes, from ``owners.log``: a line ``<cid> <robot>`` is appended before
        a robot's description is written. A line whose file is missing (a crash between the
        two, or a write that failed) is dropped; the next one for that CID, written by the add
        that stored it, wins. Descriptions without a line (the node's own dataset
        descriptions, or held before lines were kept) count towards the total only."""
        lines = self._owners.read_lines()
        owners = {}
        for line in lines:
            cid, _, robot = line.partition(" ")
            if cid in sizes:
                owners[cid] = robot
        robot_bytes: dict[str, int] = {}
        for cid, robot in owners.items():
            robot_bytes[robot] = robot_bytes.get(robot, 0) + sizes[cid]
        self._owners.compact_at_open(
            [f"{cid} {robot}" for cid, robot in owners.items()], len(lines)
        )
        return robot_bytes

    def _store(self, cid: str, description: Description, robot: str | None) -> bool:
        data = description.canonical()
        with self._lock:
            if cid in self._known:
                return False
            limit = self.max_total_bytes
            if limit is not None and self.total_bytes + len(data) > limit:
                raise KnowledgeBaseFull(cid, len(data), self.total_bytes, limit)
            if robot is not None:
                self._charge(cid, robot, len(data))
            atomic_write(self.descriptions / f"{cid}.nt", data)
            self._known.add(cid)
            self.total_bytes += len(data)
            if robot is not None:
                self._robot_bytes[robot.lower()] = self.robot_bytes(robot) + len(data)
        self.workers.add([cid])
        return True

    def _charge(self, cid: str, robot: str, size: int) -> None:
        """Check ``robot``'s share and note it as the owner of ``cid`` (before its file)."""
        used = self.robot_bytes(robot)
        limit = self.max_bytes_per_robot
        if limit is not None and used + size > limit:
            raise ShareExhausted(cid, robot, size, used, limit)
        self._owners.append(f"{cid} {robot.lower()}")

    def robot_bytes(self, robot: str) -> int:
        """What the descriptions ``robot`` added take."""
        return self._robot_bytes.get(robot.lower(), 0)

    def cids(self) -> Iterator[str]:
        with self._lock:
            yield from sorted(self._known)

    def applications(
        self, consumes: str, produces: str | None = None, limit: int = 100
    ) -> list[dict[str, Any]]:
        """Applications taking ``consumes`` (and giving ``produces``), sorted by name and IRI."""
        wanted = type_iri(consumes, "consumes")
        produced = type_iri(produces, "produces") if produces is not None else None
        apps: dict[str, dict[str, Any]] = {}
        for row in self.workers.application_rows(wanted):
            app, name, version, direction, port, port_name, media, template, attribute = row
            if app is None or direction is None or port is None:
                continue
            entry = apps.setdefault(
                app,
                {
                    "iri": app,
                    "cid": app.removeprefix("ipfs://"),
                    "name": name,
                    "version": version,
                    "inputs": {},
                    "outputs": {},
                },
            )
            ports = entry[f"{direction}s"]
            described = ports.setdefault(
                port,
                {
                    "name": port_name,
                    "iri": port,
                    "media_type": media.removeprefix(MEDIA_TYPES) if media else None,
                    "template": template,
                    "attributes": set(),
                },
            )
            if attribute is not None:
                described["attributes"].add(attribute.rsplit("#", 1)[-1])
        answer = []
        for entry in apps.values():
            for direction in ("inputs", "outputs"):
                entry[direction] = sorted(
                    (
                        {**port, "attributes": sorted(port["attributes"])}
                        for port in entry[direction].values()
                    ),
                    key=lambda port: port["name"],
                )
            if produced is not None and not any(
                MEDIA_TYPES + (port["media_type"] or "") == produced or port["template"] == produced
                for port in entry["outputs"]
            ):
                continue
            answer.append(entry)
        answer.sort(key=lambda entry: (entry["name"] or "", entry["iri"]))
        return answer[:limit]

    # ----- the ledger follower -----

    def follow(
        self, connect_ledger: ConnectLedger, interval_s: float, wait_s: float, batch: int = 1000
    ) -> None:
        """Start following the ledger's advertisements in a background thread."""
        self._follower = LedgerFollower(self, connect_ledger, interval_s, batch, wait_s)
        self._follower.start()

    def follow_state(self) -> dict[str, Any]:
        follower = self._follower
        return follower.describe() if follower is not None else {"following": False}

    def close(self) -> None:
        if self._follower is not None:
            self._follower.stop()
        self._owners.close()


def type_iri(value: str, field: str) -> str:
    """A media type (``image/jpeg``), an IANA IRI or a template's ``ipfs://<cid>``, as an IRI."""
    if value.startswith("ipfs://"):
        try:
            return f"ipfs://{parse_cid(value.removeprefix('ipfs://'), field).to_v1()}"
        except ValueError:
            raise InvalidTypeParameter(field, value) from None
    from robocloud.semantic import media_type_iri

    try:
        return media_type_iri(value)
    except SemanticError:
        raise InvalidTypeParameter(field, value) from None


STOP_TIMEOUT_S = 30.0


class LedgerFollower:
    """Reads the ledger's advertisements and indexes each advertised description once.

    Each read waits on the ledger up to ``wait_s`` for a new advertisement (a long poll), so
    a description is indexed as soon as its advertisement is mined, and an idle follower
    asks once every ``wait_s``; at most every ``interval_s`` when the ledger answers at once
    (one that does not wait, or one that failed). The wait is cut short when a pending
    description's retry falls due. Stopping does not wait for a read waiting on the ledger:
    the read's answer is dropped, as nothing of it was indexed yet.
    """

    def __init__(
        self,
        knowledge: KnowledgeBase,
        connect: ConnectLedger,
        interval_s: float,
        batch: int,
        wait_s: float = 0.0,
    ) -> None:
        self.knowledge = knowledge
        self.connect = connect
        self.interval_s = interval_s
        self.batch = batch
        self.wait_s = wait_s
        self.path = knowledge.root / "follow.json"
        self.state = FollowState.load(self.path)
        self.error: str | None = None
        self.indexed = 0
        self.clock: Callable[[], float] = time.time
        """Epoch seconds, saved as each retry's due time (so that a restart keeps backoffs)."""
        self._stop = threading.Event()
        self._indexing = threading.Lock()
        """Held while a round indexes what it read: ``stop`` waits for that, not for a read."""
        self._thread = threading.Thread(target=self._run, name="knowledge-follower", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop, letting a round that is indexing finish, for ``STOP_TIMEOUT_S`` at most: a
        round of many fetches from a slow cas may take longer."""
        self._stop.set()
        if self._indexing.acquire(timeout=STOP_TIMEOUT_S):
            self._indexing.release()

    def describe(self) -> dict[str, Any]:
        return {
            "following": True,
            "block": self.state.block,
            "log_index": self.state.log_index,
            "pending": len(self.state.pending or []),
            "refused": len(self.state.refused or {}),
            "indexed_from_ledger": self.indexed,
            "error": self.error,
        }

    def _run(self) -> None:
        while not self._stop.is_set():
            started = time.monotonic()
            try:
                more = self.poll(self.read_wait_s())
                self.error = None
            except Exception as exc:  # the ledger or cas is down: say so, try again later
                if self._stop.is_set():
                    return  # a read left waiting when the node stopped: its ledger went too
                self.error = f"{type(exc).__name__}: {exc}"[:500]
                log.warning("following the ledger's advertisements failed: %s", self.error)
                more = False
            if not more:
                self._stop.wait(max(0.0, self.interval_s - (time.monotonic() - started)))

    def read_wait_s(self) -> float:
        """``wait_s``, or less when a pending description's retry falls due sooner."""
        retries = self.state.retries
        dues = [retries[cid].due if cid in retries else 0.0 for cid in self.state.pending or []]
        return max(0.0, min([self.wait_s, *(due - self.clock() for due in dues)]))

    def poll(self, wait_s: float = 0.0) -> bool:
        """One round: read new advertisements (waiting up to ``wait_s`` for one), then retry
        the pending descriptions that are due.

        The position moves past an advertisement only once its description is indexed,
        refused or pending, so that no error while indexing one loses it. New advertisements
        come first, and at most ``MAX_RETRIES_PER_ROUND`` pending descriptions are fetched
        again, each after its backoff, all through one cas client.

        True when a full batch brought something new (there may be more to read at once).
        Each read starts past the saved position (block and log index), so a block with more
        advertisements than a batch is read in several.
        """
        state = self.state
        with self.connect() as ledger:
            advertisements = ledger.advertisements(
                since=state.block,
                after_log_index=state.log_index if state.log_index >= 0 else None,
                limit=self.batch,
                wait_s=wait_s,
            )
            with self._indexing:
                if self._stop.is_set():
                    return False
                return self._take(ledger, advertisements)

    def _take(self, ledger: LedgerReader, advertisements: list[Any]) -> bool:
        """Index what a read brought and retry what is due; see :meth:`poll`."""
        state = self.state
        state.pending, state.refused = state.pending or [], state.refused or {}
        nodes = _storage_nodes(
            ledger,
            {
                ad.advertiser
                for ad in advertisements
                if ad.description is not None and ad.description not in self.knowledge
            },
        )
        with _RoundCas(self.knowledge.connect_cas) as cas:
            progressed = False
            for ad in advertisements:
                if (ad.block_number, ad.log_index) <= (state.block, state.log_index):
                    continue
                cid = ad.description
                if not (
                    cid is None
                    or cid in state.refused
                    or cid in self.knowledge
                    or cid in state.retries
                    or cid in state.pending
                ):
                    charged = None if ad.advertiser in nodes else ad.advertiser
                    self._attempt(cid, charged, cas, new=True)
                state.block, state.log_index = ad.block_number, ad.log_index
                progressed = True
            retried = self._retry_due(cas)
        if progressed or retried:
            state.save(self.path)
        return progressed and len(advertisements) >= self.batch

    def _retry_due(self, cas: _RoundCas) -> bool:
        now = self.clock()
        retries = self.state.retries
        due = [
            cid for cid in self.state.pending or [] if cid not in retries or retries[cid].due <= now
        ][:MAX_RETRIES_PER_ROUND]
        for cid in due:
            if cas.unavailable:
                break
            self._attempt(cid, retries[cid].robot if cid in retries else None, cas, new=False)
        return bool(due)

    def _attempt(self, cid: str, robot: str | None, cas: _RoundCas, *, new: bool) -> None:
        """Index ``cid``; when that fails, keep it pending with its backoff, or refuse it once
        ``MAX_ATTEMPTS`` fetches failed. Once cas was unreachable this round, a new CID is
        queued without a fetch."""
        pending, refused, retries = self.state.pending, self.state.refused, self.state.retries
        assert pending is not None
        assert refused is not None
        failure = (
            "cas was unreachable" if cas.unavailable else self._index(cid, robot, refused, cas)
        )
        if failure is None:
            if not new:
                pending.remove(cid)
            retries.pop(cid, None)
            return
        previous = retries.get(cid, Retry(0, 0.0))
        attempts = previous.attempts + (0 if cas.unavailable else 1)
        if attempts >= MAX_ATTEMPTS:
            log.warning("advertised description %s refused after %d attempts", cid, attempts)
            _refuse(refused, cid, f"not fetched after {attempts} attempts: {failure}")
            if not new:
                pending.remove(cid)
            retries.pop(cid, None)
            return
        wait = min(self.interval_s * 2 ** min(max(attempts - 1, 0), 32), MAX_BACKOFF_S)
        retries[cid] = Retry(attempts, self.clock() + wait, robot)
        if new:
            pending.append(cid)
            for dropped in pending[:-MAX_PENDING]:
                retries.pop(dropped, None)
                _refuse(refused, dropped, f"dropped: more than {MAX_PENDING} descriptions pending")
            del pending[:-MAX_PENDING]

    def _index(
        self, cid: str, robot: str | None, refused: dict[str, str], cas: _RoundCas
    ) -> str | None:
        """None once the description is indexed or refused for good; else why to retry it.

        One past its advertiser's share is refused for good: kept pending, one robot's
        advertisements could take every place of the pending list."""
        try:
            indexed = self.knowledge.add(cid, cas, robot=robot)
        except DescriptionRefused as exc:
            log.info("advertised description %s refused: %s", cid, exc.reason)
            _refuse(refused, cid, str(exc.reason))
            return None
        except ShareExhausted as exc:
            log.info("advertised description %s refused: %s", cid, exc)
            _refuse(refused, cid, str(exc))
            return None
        except DescriptionNotFound as exc:
            log.info("advertised description %s not fetched yet: %s", cid, exc)
            return str(exc)
        except CasUnavailable as exc:
            log.info("advertised description %s not fetched yet: %s", cid, exc)
            cas.unavailable = True
            return str(exc)
        except ValueError as exc:  # a CID the chain holds that is not a valid CID
            _refuse(refused, cid, str(exc))
            return None
        except Exception as exc:  # a full disk or knowledge base, a bug: try it again later
            log.warning(
                "indexing advertised description %s failed, kept for a retry: %s: %s",
                cid,
                type(exc).__name__,
                exc,
            )
            return f"{type(exc).__name__}: {exc}"
        if indexed.new:
            self.indexed += 1
        return None


def _storage_nodes(ledger: LedgerReader, advertisers: set[str]) -> set[str]:
    """The advertisers holding the storage node role. Their descriptions are the datasets of
    every robot's bags, charged to no one here as a node's own are on its own knowledge base:
    charged to the node, another node's datasets were refused after some 25,000 bags."""
    nodes = set()
    for advertiser in advertisers:
        robot = ledger.robot(advertiser)
        if robot is not None and Role.STORAGE_NODE.value in robot.roles:
            nodes.add(advertiser)
    return nodes


def _refuse(refused: dict[str, str], cid: str, why: str) -> None:
    if len(refused) < MAX_REFUSED:
        refused[cid] = why[:500]


class _RoundCas:
    """One cas client for a round of the follower, opened at its first fetch.

    ``unavailable`` is set once cas could not be asked: the rest of the round fetches nothing.
    """

    def __init__(self, connect: Connect) -> None:
        self._connect = connect
        self._stack = ExitStack()
        self._cas: CasReader | None = None
        self.unavailable = False

    def __enter__(self) -> _RoundCas:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stack.close()

    def get(self, cid: CID | str, *, max_size: int | None = None) -> bytes:
        if self._cas is None:
            self._cas = self._stack.enter_context(self._connect())
        return self._cas.get(cid, max_size=max_size)
