"""The ledger follower over real files, a stand-in ledger and a stand-in cas: an error while
indexing one advertisement keeps it pending, and descriptions cas does not hold are retried
with a backoff, a bounded number per round, then refused."""

from __future__ import annotations

import errno
import json
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import pytest

from robocloud import semantic
from robocloud.cid import CID
from robocloud.errors import NotFoundError
from robocloud.unixfs import import_bytes
from services.storage import knowledge
from services.storage.knowledge import (
    MAX_ATTEMPTS,
    FollowState,
    KnowledgeBase,
    LedgerFollower,
    Retry,
)
from services.storage.sparql import SparqlWorkers
from tests.clock import Clock

EXAMPLES = Path(__file__).resolve().parents[4] / "ontology" / "examples"


ROBOT = "0x1a642f0E3c3aF545E7AcBD38b07251B3990914F1"
OTHER_ROBOT = "0x5B38Da6a701c568545dCfcB03FcB875f56beddC4"


@dataclass
class Ad:
    block_number: int
    log_index: int
    description: str | None
    advertiser: str = ROBOT


@dataclass
class Robot:
    roles: tuple[str, ...]


class Ledger:
    def __init__(self) -> None:
        self.ads: list[Ad] = []
        self.roles: dict[str, tuple[str, ...]] = {}
        self.waits: list[float] = []

    def robot(self, address: str) -> Robot | None:
        """As ``GET /v1/robots/{address}`` answers: None for one never registered."""
        roles = self.roles.get(address)
        return None if roles is None else Robot(roles)

    def advertisements(
        self, *, since: int, limit: int, after_log_index: int | None = None, wait_s: float = 0
    ) -> list[Ad]:
        """As the ledger's ``GET /v1/advertisements`` answers (the index's query), the wait
        asked for noted and not waited."""
        self.waits.append(wait_s)
        position = (since, -1 if after_log_index is None else after_log_index)
        return [ad for ad in self.ads if (ad.block_number, ad.log_index) > position][:limit]


class Cas:
    """Holds ``blobs``; counts each client opened and each fetch."""

    def __init__(self) -> None:
        self.blobs: dict[str, bytes] = {}
        self.clients = 0
        self.fetched: list[str] = []

    def put(self, name: str) -> str:
        data = semantic.parse_description((EXAMPLES / f"{name}.ttl").read_bytes()).canonical()
        cid = str(import_bytes(data)[1])
        self.blobs[cid] = data
        return cid

    @contextmanager
    def connect(self) -> Iterator[Cas]:
        self.clients += 1
        yield self

    def get(self, cid: CID | str, *, max_size: int | None = None) -> bytes:
        self.fetched.append(str(cid))
        try:
            return self.blobs[str(cid)]
        except KeyError:
            raise NotFoundError(404, "not_found", f"no block {cid}") from None

    def round(self) -> tuple[int, int]:
        """Clients opened and fetches since the last call."""
        counts = (self.clients, len(self.fetched))
        self.clients, self.fetched = 0, []
        return counts


class Workers:
    def __init__(self) -> None:
        self.added: list[str] = []

    def add(self, cids: list[str]) -> None:
        self.added.extend(cids)


@pytest.fixture
def cas() -> Cas:
    return Cas()


@pytest.fixture
def ledger() -> Ledger:
    return Ledger()


@pytest.fixture
def clock() -> Clock:
    return Clock(1_800_000_000.0)


def connecting_to(ledger: Ledger) -> Callable[[], AbstractContextManager[Ledger]]:
    """What a follower connects with: ``ledger`` itself, each time."""

    @contextmanager
    def connect_ledger() -> Iterator[Ledger]:
        yield ledger

    return connect_ledger


def follower_of(
    kb: KnowledgeBase, ledger: Ledger, clock: Clock, batch: int = 1000, wait_s: float = 0.0
) -> LedgerFollower:
    """A follower of ``ledger`` feeding ``kb``, on ``clock``; a new one is a restart."""
    follower = LedgerFollower(kb, connecting_to(ledger), 10.0, batch, wait_s)
    follower.clock = clock
    return follower


def knowledge_base(root: Path, cas: Cas, **limits: int) -> KnowledgeBase:
    return KnowledgeBase(root / "knowledge", cast(SparqlWorkers, Workers()), cas.connect, **limits)


@pytest.fixture
def make_follower(tmp_path: Path, cas: Cas, ledger: Ledger, clock: Clock) -> Any:
    kb = knowledge_base(tmp_path, cas)
    return lambda batch=1000: follower_of(kb, ledger, clock, batch)


def bogus_cid(n: int) -> str:
    return str(import_bytes(f"not in cas {n}".encode())[1])


def test_a_disk_error_storing_one_description_keeps_it_pending(
    make_follower: Any, cas: Cas, ledger: Ledger, clock: Clock, monkeypatch: pytest.MonkeyPatch
) -> None:
    file_cid, app_cid, task_cid = cas.put("file"), cas.put("application"), cas.put("task")
    follower = make_follower()
    real_write = knowledge.atomic_write
    disk_full = True

    def atomic_write(path: Path, data: bytes) -> None:
        if disk_full and path.name == f"{app_cid}.nt":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real_write(path, data)

    monkeypatch.setattr(knowledge, "atomic_write", atomic_write)
    ledger.ads += [Ad(1, 0, file_cid), Ad(2, 0, app_cid), Ad(3, 0, task_cid)]
    follower.poll()

    kb = follower.knowledge
    assert (file_cid in kb, app_cid in kb, task_cid in kb) == (True, False, True)
    assert (follower.state.block, follower.state.log_index) == (3, 0)
    assert follower.state.pending == [app_cid]
    assert follower.state.refused == {}
    saved = json.loads((kb.root / "follow.json").read_text())
    assert saved["pending"] == [app_cid]
    assert saved["retries"][app_cid]["attempts"] == 1

    disk_full = False
    restarted = make_follower()
    assert restarted.state.pending == [app_cid]
    clock.now += 3600
    restarted.poll()
    assert app_cid in kb
    assert (restarted.state.pending, restarted.state.retries) == ([], {})


def test_a_description_past_the_knowledge_bases_size_stays_pending_until_there_is_room(
    tmp_path: Path, cas: Cas, ledger: Ledger, clock: Clock
) -> None:
    """Not the description's fault, so not refused for good: the operator may raise the bound."""
    file_cid, app_cid = cas.put("file"), cas.put("application")
    kb = knowledge_base(tmp_path, cas, max_total_bytes=len(cas.blobs[file_cid]))
    follower = follower_of(kb, ledger, clock)
    ledger.ads += [Ad(1, 0, file_cid), Ad(2, 0, app_cid)]
    follower.poll()
    assert (file_cid in kb, app_cid in kb) == (True, False)
    assert follower.state.pending == [app_cid]
    assert follower.state.refused == {}
    assert kb.total_bytes == len(cas.blobs[file_cid])
    assert sorted(path.stem for path in kb.descriptions.iterdir()) == [file_cid]

    kb.max_total_bytes = len(cas.blobs[file_cid]) + len(cas.blobs[app_cid])
    clock.now += 3600
    follower.poll()
    assert app_cid in kb
    assert (follower.state.pending, follower.state.refused) == ([], {})
    assert kb.total_bytes == kb.max_total_bytes


def test_a_description_past_its_advertisers_share_is_refused_for_good(
    tmp_path: Path, cas: Cas, ledger: Ledger, clock: Clock
) -> None:
    """The advertiser is charged, a pending one's too once it is fetched at last; one past the
    share is refused, not kept pending, and other robots' descriptions go on."""
    file_cid, app_cid, task_cid = cas.put("file"), cas.put("application"), cas.put("task")
    app = cas.blobs.pop(app_cid)  # not in cas yet: pending
    kb = knowledge_base(tmp_path, cas, max_bytes_per_robot=len(cas.blobs[file_cid]))
    follower = follower_of(kb, ledger, clock)
    ledger.ads += [Ad(1, 0, file_cid), Ad(2, 0, app_cid), Ad(3, 0, task_cid, OTHER_ROBOT)]
    follower.poll()
    assert (file_cid in kb, app_cid in kb, task_cid in kb) == (True, False, True)
    assert follower.state.pending == [app_cid]
    assert FollowState.load(kb.root / "follow.json").retries[app_cid].robot == ROBOT
    assert kb.robot_bytes(ROBOT) == len(cas.blobs[file_cid])
    assert kb.robot_bytes(OTHER_ROBOT.lower()) == len(cas.blobs[task_cid])

    cas.blobs[app_cid] = app
    clock.now += 3600
    follower_of(kb, ledger, clock).poll()  # a restart: the robot charged is read again
    assert app_cid not in kb
    saved = FollowState.load(kb.root / "follow.json")
    assert saved.pending == []
    assert saved.refused is not None
    assert f"{ROBOT} holds {len(cas.blobs[file_cid])} bytes" in saved.refused[app_cid]
    assert "past its share" in saved.refused[app_cid]
    assert sorted(path.stem for path in kb.descriptions.iterdir()) == sorted([file_cid, task_cid])


def test_a_storage_nodes_dataset_descriptions_are_charged_to_no_one(
    tmp_path: Path, cas: Cas, ledger: Ledger, clock: Clock
) -> None:
    """Another node advertises the datasets of every robot's bags: charged to it, they were
    refused once its share was spent. A robot that lost the role is charged again."""
    file_cid, app_cid, task_cid = cas.put("file"), cas.put("application"), cas.put("task")
    kb = knowledge_base(tmp_path, cas, max_bytes_per_robot=len(cas.blobs[file_cid]))
    follower = follower_of(kb, ledger, clock)
    ledger.roles = {ROBOT: ("storage_node",), OTHER_ROBOT: ()}
    ledger.ads += [Ad(1, 0, file_cid), Ad(2, 0, app_cid)]
    follower.poll()
    assert (file_cid in kb, app_cid in kb) == (True, True)
    assert kb.robot_bytes(ROBOT) == 0

    ledger.roles[ROBOT] = ()
    ledger.ads += [Ad(3, 0, task_cid)]
    follower.poll()
    assert kb.robot_bytes(ROBOT) == len(cas.blobs[task_cid])


def test_a_block_with_more_advertisements_than_a_batch_is_read_past(
    make_follower: Any, cas: Cas, ledger: Ledger
) -> None:
    """A stranger's block of more advertisements than one read returns stopped the follower
    for good: each read started at the block again and brought back the same batch."""
    described = [cas.put(name) for name in ("file", "application", "task", "dataset")]
    ledger.ads += [Ad(7, index, cid) for index, cid in enumerate(described[:3])]
    ledger.ads.append(Ad(9, 0, described[3]))
    follower = make_follower(batch=2)

    assert follower.poll() is True  # a full batch: there may be more at once
    assert (follower.state.block, follower.state.log_index) == (7, 1)
    assert follower.poll() is True
    assert (follower.state.block, follower.state.log_index) == (9, 0)
    assert follower.poll() is False
    assert all(cid in follower.knowledge for cid in described)
    assert (follower.state.block, follower.state.log_index) == (9, 0)
    saved = json.loads((follower.knowledge.root / "follow.json").read_text())
    assert (saved["block"], saved["log_index"]) == (9, 0)


def test_pending_descriptions_back_off_are_bounded_per_round_and_refused_at_last(
    make_follower: Any,
    cas: Cas,
    ledger: Ledger,
    clock: Clock,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(knowledge, "MAX_RETRIES_PER_ROUND", 7)
    bogus = [bogus_cid(n) for n in range(20)]
    ledger.ads += [Ad(1 + n, 0, cid) for n, cid in enumerate(bogus)]
    follower = make_follower()

    follower.poll()
    assert cas.round() == (1, 20)  # each new advertisement fetched once, through one client
    assert follower.state.pending == bogus

    follower.poll()
    assert cas.round() == (0, 0)  # none is due yet: nothing fetched again

    honest = cas.put("file")
    ledger.ads.append(Ad(100, 0, honest))
    follower.poll()
    assert cas.round() == (1, 1)
    assert honest in follower.knowledge

    clock.now += 20  # two poll intervals: all are due, only 7 are fetched again this round
    follower.poll()
    assert cas.round() == (1, 7)
    assert {follower.state.retries[cid].attempts for cid in bogus} == {1, 2}
    follower.poll()
    follower.poll()
    assert cas.round() == (2, 13)  # the rest, then nothing left due
    follower.poll()
    assert cas.round() == (0, 0)

    restarted = make_follower()  # the backoff survives a restart
    assert restarted.state.retries == follower.state.retries
    for _ in range(MAX_ATTEMPTS * 3):
        clock.now += knowledge.MAX_BACKOFF_S
        restarted.poll()
    assert restarted.state.pending == []
    assert restarted.state.retries == {}
    assert set(restarted.state.refused or {}) == set(bogus)
    assert (restarted.state.refused or {})[bogus[0]].startswith(
        f"not fetched after {MAX_ATTEMPTS} attempts: cas does not have"
    )
    assert len(cas.fetched) == len(bogus) * (MAX_ATTEMPTS - 2)
    cas.round()
    clock.now += knowledge.MAX_BACKOFF_S
    restarted.poll()
    assert cas.round() == (0, 0)


def test_a_place_saved_before_retries_were_kept_still_loads(tmp_path: Path) -> None:
    path = tmp_path / "follow.json"
    path.write_text(
        json.dumps({"block": 7, "log_index": 2, "pending": ["bafyold"], "refused": {"x": "why"}})
    )
    assert FollowState.load(path) == FollowState(7, 2, ["bafyold"], {"x": "why"}, {})
    FollowState(7, 2, ["bafyold"], {}, {"bafyold": Retry(3, 12.5)}).save(path)
    assert FollowState.load(path).retries == {"bafyold": Retry(3, 12.5)}


def test_a_read_waits_on_the_ledger_until_a_pending_retry_falls_due(
    tmp_path: Path, cas: Cas, ledger: Ledger, clock: Clock
) -> None:
    """The follower asked the ledger every 2 s; it now asks it to wait for the next
    advertisement, no longer than until the next pending description is due again."""
    missing = bogus_cid(1)
    follower = follower_of(knowledge_base(tmp_path, cas), ledger, clock, wait_s=20)
    assert follower.read_wait_s() == 20
    ledger.ads.append(Ad(1, 0, missing))
    follower.poll(follower.read_wait_s())
    due = follower.state.retries[missing].due
    assert follower.read_wait_s() == pytest.approx(due - clock.now)
    assert 0 < follower.read_wait_s() < 20
    clock.now = due + 1
    assert follower.read_wait_s() == 0
    assert ledger.waits == [20]


class WaitingLedger(Ledger):
    """A ledger whose read of advertisements waits until ``answer`` is set (10 s at most)."""

    def __init__(self) -> None:
        super().__init__()
        self.reading = threading.Event()
        self.answer = threading.Event()

    def advertisements(
        self, *, since: int, limit: int, after_log_index: int | None = None, wait_s: float = 0
    ) -> list[Ad]:
        self.reading.set()
        self.answer.wait(10)
        return super().advertisements(
            since=since, limit=limit, after_log_index=after_log_index, wait_s=wait_s
        )


def test_stopping_does_not_wait_for_a_read_waiting_on_the_ledger(tmp_path: Path, cas: Cas) -> None:
    """A read may wait on the ledger for 20 s; the storage node stopping waited for it (and a
    follower of a ledger that never answered held the stop 30 s). It stops at once now, and
    what the read brings afterwards is dropped, not indexed into a closed knowledge base."""
    ledger = WaitingLedger()
    kb = knowledge_base(tmp_path, cas)
    kb.follow(connecting_to(ledger), 0.05, 20)
    assert ledger.reading.wait(10)
    ledger.ads.append(Ad(1, 0, cas.put("file")))

    kb.close()

    assert not ledger.answer.is_set()
    ledger.answer.set()
    follower = kb._follower
    assert follower is not None
    follower._thread.join(10)
    assert not follower._thread.is_alive()
    assert (follower.state.block, len(kb)) == (0, 0)
    assert not (kb.root / "follow.json").exists()


class VanishingLedger(WaitingLedger):
    """A ledger whose waiting read fails once answered: the service went away meanwhile."""

    def advertisements(
        self, *, since: int, limit: int, after_log_index: int | None = None, wait_s: float = 0
    ) -> list[Ad]:
        super().advertisements(
            since=since, limit=limit, after_log_index=after_log_index, wait_s=wait_s
        )
        raise ConnectionError("the ledger closed the connection")


def test_a_read_that_fails_after_the_stop_is_not_reported(
    tmp_path: Path, cas: Cas, caplog: pytest.LogCaptureFixture
) -> None:
    """When a node stops, its ledger often stops too, and the read left waiting then fails:
    the follower logged that failure as a warning after the node had stopped."""
    ledger = VanishingLedger()
    kb = knowledge_base(tmp_path, cas)
    kb.follow(connecting_to(ledger), 0.05, 20)
    assert ledger.reading.wait(10)
    kb.close()
    with caplog.at_level("WARNING", logger="robocloud.storage.knowledge"):
        ledger.answer.set()
        follower = kb._follower
        assert follower is not None
        follower._thread.join(10)
    assert not follower._thread.is_alive()
    assert [record.getMessage() for record in caplog.records] == []
    assert follower.error is None
