"""The knowledge base keeps what it indexed through a restart and a kill -9 without fetching it
again (cas is down when it comes back), follows descriptions advertised on the ledger, and
rebuilds itself from cas and the ledger's advertisements when its files are lost."""

from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import pytest

from robocloud import semantic
from robocloud.cas import Cas
from robocloud.cid import parse_cid
from robocloud.errors import ServerError
from robocloud.identity import Identity
from robocloud.knowledge import Knowledge
from robocloud.ledger import Ledger
from robocloud.semantic import Description
from tests.conftest import ServiceFactory
from tests.procs import REPO, ServiceProcess
from tests.waiting import wait_for

EXAMPLES = REPO / "ontology" / "examples"
METADATA = bytes.fromhex("01551220") + bytes(range(32))
ASK = "PREFIX rc: <https://w3id.org/robocloud#> ASK {{ <{iri}> a rc:{kind} }}"


def example(kind: str) -> Description:
    return semantic.parse_description((EXAMPLES / f"{kind}.ttl").read_bytes())


def holds(storage: ServiceProcess, iri: str, kind: str) -> bool:
    answer = httpx.get(
        f"{storage.url}/v1/knowledge/sparql",
        params={"query": ASK.format(iri=iri, kind=kind)},
        timeout=30,
    )
    assert answer.status_code == 200, answer.text
    return bool(answer.json()["boolean"])


def descriptions_of(storage: ServiceProcess) -> set[str]:
    return {path.stem for path in (storage.data_dir / "knowledge" / "descriptions").glob("*.nt")}


FILE = ("ipfs://bafkreifhyd2reqnaxb6vmuv3gwnyum4osowzkclmxa2qdsj3fhkderxyem", "File")
APP = ("ipfs://bafkreia357kjlhicbaks5xy6g5ridjm6wevmf6ccufgzsdrlpfyi6ydb34", "Application")
TASK = ("ipfs://bafkreida5gq3v6rabjib2uiqzefbdra2cxrzx2sctf56h2igs73ndf2ouu", "Task")


def storage_beside(
    service_factory: ServiceFactory, cas: ServiceProcess, **env: str
) -> ServiceProcess:
    """A storage service over ``cas`` that neither anchors nor follows the ledger."""
    return service_factory(
        "storage",
        {
            "ROBOCLOUD_CAS_URL": cas.url,
            "ROBOCLOUD_STORAGE_ANCHOR": "false",
            "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
            **{f"ROBOCLOUD_{name.upper()}": value for name, value in env.items()},
        },
    )


def refusal(
    storage: ServiceProcess, cas: ServiceProcess, identity: Identity, description: Description
) -> ServerError:
    """The error storing ``description`` as ``identity`` ends in."""
    with (
        Cas(cas.url, identity) as cas_client,
        Knowledge(storage.url, identity) as knowledge,
        pytest.raises(ServerError) as refused,
    ):
        knowledge.store(description, cas_client)
    return refused.value


def test_restart_and_kill_9_keep_every_description_without_cas(
    service_factory: ServiceFactory,
) -> None:
    cas = service_factory("cas")
    storage = storage_beside(service_factory, cas)
    identity = Identity.generate()
    with Cas(cas.url, identity) as cas_client, Knowledge(storage.url, identity) as knowledge:
        knowledge.store(example("file"), cas_client)
        knowledge.store(example("application"), cas_client)
    cas.stop()
    storage.restart()
    assert holds(storage, *FILE)
    assert holds(storage, *APP)
    with Knowledge(storage.url) as knowledge:
        assert [app["name"] for app in knowledge.applications("image/jpeg")] == ["blur_faces"]

    cas.start()
    with Cas(cas.url, identity) as cas_client, Knowledge(storage.url, identity) as knowledge:
        knowledge.store(example("task"), cas_client)
    storage.stop(kill=True)
    cas.stop()
    storage.start()
    for iri, kind in (FILE, APP, TASK):
        assert holds(storage, iri, kind)
    assert httpx.get(f"{storage.url}/v1/knowledge").json()["descriptions"] == 3


def test_advertised_descriptions_are_indexed_and_rebuilt_when_the_files_are_lost(
    service_factory: ServiceFactory, tmp_path: Path
) -> None:
    ledger = service_factory("ledger", {"ROBOCLOUD_LEDGER_POLL_INTERVAL_S": "0.2"})
    cas = service_factory("cas")
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_CAS_URL": cas.url,
            "ROBOCLOUD_LEDGER_URL": ledger.url,
            "ROBOCLOUD_STORAGE_ANCHOR": "false",
            "ROBOCLOUD_STORAGE_REGISTER": "false",
            "ROBOCLOUD_KNOWLEDGE_POLL_S": "0.2",
        },
    )
    identity = Identity.generate()
    broken = semantic.parse_canonical(example("task").canonical().replace(b'"3"^^', b'"0"^^'))
    with (
        Cas(cas.url, identity) as cas_client,
        Ledger.connect(ledger.url, identity, receipt_timeout_s=30) as robot,
    ):
        robot.faucet()
        robot.register(METADATA)
        for description in (example("file"), example("application"), broken):
            stored = cas_client.add_bytes(description.canonical())
            assert stored == description.cid()
        robot.advertise(parse_cid(FILE[0][7:], "cid").binary, example("file").cid().binary)
        robot.advertise(parse_cid(APP[0][7:], "cid").binary, example("application").cid().binary)
        robot.advertise(parse_cid(TASK[0][7:], "cid").binary, broken.cid().binary)
        robot.advertise(parse_cid(TASK[0][7:], "cid").binary)

    def follow() -> dict[str, object]:
        return dict(httpx.get(f"{storage.url}/v1/knowledge", timeout=10).json()["ledger"])

    wait_for(lambda: follow()["refused"] == 1 and follow()["indexed_from_ledger"] == 2, "indexing")
    assert holds(storage, *FILE)
    assert holds(storage, *APP)
    assert not holds(storage, *TASK)
    expected = {str(example("file").cid()), str(example("application").cid())}
    assert descriptions_of(storage) == expected
    assert follow()["error"] is None

    storage.stop()
    shutil.rmtree(storage.data_dir / "knowledge")
    storage.start()
    wait_for(lambda: descriptions_of(storage) == expected, "the knowledge base to rebuild")
    wait_for(lambda: follow()["refused"] == 1, "the broken description to be refused again")
    assert holds(storage, *FILE)
    assert holds(storage, *APP)
    assert not holds(storage, *TASK)


def test_a_description_past_the_knowledge_bases_size_is_refused_and_nothing_kept(
    service_factory: ServiceFactory,
) -> None:
    """Each SPARQL worker holds the whole graph; past the bound the next one is 507 naming the
    sizes, the bound counts what is on disk after a restart, and raising it makes room."""
    file, application, task = example("file"), example("application"), example("task")
    room = len(file.canonical()) + len(application.canonical())
    cas = service_factory("cas")
    storage = storage_beside(service_factory, cas, knowledge_max_total_bytes=str(room))
    identity = Identity.generate()

    def refused_task() -> None:
        refused = refusal(storage, cas, identity, task)
        assert (refused.status, refused.code) == (507, "knowledge_base_full")
        assert refused.details == {
            "cid": str(task.cid()),
            "size": len(task.canonical()),
            "used": room,
            "limit": room,
        }
        assert descriptions_of(storage) == {str(file.cid()), str(application.cid())}
        assert not holds(storage, *TASK)
        state = httpx.get(f"{storage.url}/v1/knowledge", timeout=10).json()
        assert (state["descriptions"], state["bytes"], state["max_bytes"]) == (2, room, room)

    with Cas(cas.url, identity) as cas_client, Knowledge(storage.url, identity) as knowledge:
        knowledge.store(file, cas_client)
        knowledge.store(application, cas_client)
        assert knowledge.add(file.cid())["new"] is False  # known ones are still answered
    refused_task()
    storage.restart()
    refused_task()

    storage.stop()
    storage.env["ROBOCLOUD_KNOWLEDGE_MAX_TOTAL_BYTES"] = str(room + len(task.canonical()))
    storage.start()
    with Cas(cas.url, identity) as cas_client, Knowledge(storage.url, identity) as knowledge:
        knowledge.store(task, cas_client)
    assert holds(storage, *TASK)


def test_a_robot_past_its_share_is_refused_and_others_go_on_across_a_restart(
    service_factory: ServiceFactory,
) -> None:
    file, application, task = example("file"), example("application"), example("task")
    share = len(application.canonical())  # more than the file, less than the file and another
    cas = service_factory("cas")
    storage = storage_beside(service_factory, cas, knowledge_max_bytes_per_robot=str(share))
    greedy, other = Identity.generate(), Identity.generate()

    def refused(description: Description) -> None:
        refused = refusal(storage, cas, greedy, description)
        assert (refused.status, refused.code) == (507, "quota_exceeded")
        assert refused.details == {
            "cid": str(description.cid()),
            "robot": greedy.address,
            "size": len(description.canonical()),
            "used": len(file.canonical()),
            "limit": share,
        }
        assert str(description.cid()) not in descriptions_of(storage)

    with Cas(cas.url, greedy) as cas_client, Knowledge(storage.url, greedy) as knowledge:
        knowledge.store(file, cas_client)
    refused(application)
    with Cas(cas.url, other) as cas_client, Knowledge(storage.url, other) as knowledge:
        knowledge.store(application, cas_client)
    storage.restart()
    refused(task)
    assert descriptions_of(storage) == {str(file.cid()), str(application.cid())}
    with Knowledge(storage.url, greedy) as knowledge:
        assert knowledge.add(application.cid())["new"] is False  # held: nothing to charge
    assert holds(storage, *APP)
