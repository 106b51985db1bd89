"""The proof, consistency and epoch routes: answers as ARCHITECTURE.md says, errors naming inputs.

The service runs alone with anchoring off: no epoch is ever cut, so every record answers 409.
"""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from robocloud import merkle
from robocloud.identity import Identity
from robocloud.templates import canonical_record
from tests.integration.services.storage.counter import counter_record, write_counter_records
from tests.procs import ServiceProcess

WRITER = Identity.generate()


def leaf(i: int) -> bytes:
    return merkle.leaf_hash(canonical_record(counter_record(WRITER.address, i)))


@pytest.fixture(scope="module")
def storage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    data_dir = tmp_path_factory.mktemp("storage")
    with ServiceProcess(
        data_dir=data_dir, name="storage", env={"ROBOCLOUD_STORAGE_ANCHOR": "false"}
    ) as process:
        write_counter_records(process, WRITER, 0, 3)
        yield process


def error(response: httpx.Response, status: int, code: str) -> dict[str, object]:
    assert response.status_code == status, response.text
    body = response.json()["error"]
    assert body["code"] == code, body
    return dict(body["details"])


def test_consistency_proof_verifies(storage: ServiceProcess) -> None:
    answer = httpx.get(f"{storage.url}/v1/templates/imu@1/consistency?first=1&second=3").json()
    leaves = [leaf(i) for i in range(3)]
    assert answer["first_root"] == merkle.root(leaves[:1]).hex()
    assert answer["second_root"] == merkle.root(leaves).hex()
    merkle.verify_consistency(
        1,
        3,
        merkle.root(leaves[:1]),
        merkle.root(leaves),
        [bytes.fromhex(node) for node in answer["proof"]],
    )


@pytest.mark.parametrize(
    ("query", "field", "code"),
    [
        ("first=1&second=4", "second", "invalid_parameter"),
        ("first=3&second=2", "first", "invalid_parameter"),
        ("first=abc&second=2", "first", "invalid_parameter"),
        ("first=-1&second=2", "first", "invalid_parameter"),
        ("first=1&second=" + "9" * 30, "second", "invalid_parameter"),
        ("first=1", "second", "missing_parameter"),
        ("second=1", "first", "missing_parameter"),
    ],
)
def test_bad_consistency_parameters_are_named(
    storage: ServiceProcess, query: str, field: str, code: str
) -> None:
    response = httpx.get(f"{storage.url}/v1/templates/imu@1/consistency?{query}")
    assert error(response, 400, code)["field"] == field


def test_consistency_of_a_malformed_or_unknown_template(storage: ServiceProcess) -> None:
    bad = httpx.get(f"{storage.url}/v1/templates/Imu@1/consistency?first=0&second=0")
    assert error(bad, 400, "invalid_template_id") == {"field": "id", "template": "Imu@1"}
    unknown = httpx.get(f"{storage.url}/v1/templates/gps@1/consistency?first=0&second=0")
    assert error(unknown, 404, "template_not_found") == {"template": "gps@1"}
    assert not (storage.data_dir / "logs" / "gps@1").exists()


@pytest.mark.parametrize(
    "record_id", ["IMU-1-0", "imu-1", "imu-1-x", "imu-0-1", "imu-1-01", "i" * 300]
)
def test_a_malformed_record_id_is_refused(storage: ServiceProcess, record_id: str) -> None:
    response = httpx.get(f"{storage.url}/v1/records/{record_id}/proof")
    assert error(response, 400, "invalid_record_id") == {"field": "id", "id": record_id[:200]}


def test_missing_and_unanchored_records(storage: ServiceProcess) -> None:
    missing = httpx.get(f"{storage.url}/v1/records/imu-1-3/proof")
    assert error(missing, 404, "record_not_found") == {"id": "imu-1-3"}
    unknown = httpx.get(f"{storage.url}/v1/records/gps-1-0/proof")
    assert error(unknown, 404, "record_not_found") == {"id": "gps-1-0"}
    waiting = httpx.get(f"{storage.url}/v1/records/imu-1-2/proof")
    assert error(waiting, 409, "not_anchored") == {"id": "imu-1-2", "epoch": 1}


def test_epochs_that_are_malformed_or_not_cut(storage: ServiceProcess) -> None:
    assert error(httpx.get(f"{storage.url}/v1/epochs/abc"), 400, "invalid_parameter") == {
        "field": "epoch",
        "value": "abc",
    }
    assert error(httpx.get(f"{storage.url}/v1/epochs/1"), 404, "epoch_not_found") == {"epoch": 1}
    # Beyond SQLite's 64-bit integers: binding one raised OverflowError, a 500.
    for epoch in (2**63 - 1, 2**63, 10**19 - 1):
        beyond = httpx.get(f"{storage.url}/v1/epochs/{epoch}")
        assert error(beyond, 404, "epoch_not_found") == {"epoch": epoch}
    assert error(httpx.get(f"{storage.url}/v1/epochs/{10**19}"), 400, "invalid_parameter") == {
        "field": "epoch",
        "value": str(10**19),
    }
    node = httpx.get(f"{storage.url}/v1/node").json()
    assert node["anchoring"] is False
    assert node["last_epoch"] == 0
