"""``dag/import`` of CARv2 through a real cas: pinned and exported as its CARv1 payload is; a
malformed CARv2 is 400 ``invalid_car`` naming what is wrong, and stores nothing."""

from __future__ import annotations

import io
import json

import httpx
import pytest

from robocloud.car import CarReader, write_car
from robocloud.cid import CID
from robocloud.client import ServiceClient
from robocloud.errors import ApiError
from robocloud.unixfs import ImportParams, import_bytes
from tests.integration.services.cas.conftest import (
    error_of,
    multipart,
    pin_list,
    repo_stat,
    store_unchanged,
)
from tests.procs import ServiceProcess
from tests.unit.robocloud.test_car import SPEC_CARV2_BASIC, SPEC_CARV2_ROOT, bit, carv2


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    """This module's tests share one cas; each uses its own data and checks changes only."""
    return shared_cas_service


def dag_import(client: ServiceClient, car: bytes) -> list[dict[str, object]]:
    body, content_type = multipart(("x.car", car))
    response = client.request(
        "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
    )
    return [json.loads(line) for line in response.text.splitlines()]


def dag_export(service: ServiceProcess, root: CID | str) -> bytes:
    response = httpx.post(f"{service.url}/api/v0/dag/export", params={"arg": str(root)})
    assert response.status_code == 200, response.text
    return response.content


def a_dag(seed: int) -> tuple[CID, bytes]:
    """A four-block UnixFS file (a root and three raw chunks) of its own bytes, as a CARv1."""
    blocks, root = import_bytes(
        bytes([seed]) * 1000 + bytes(range(256)) * 8, ImportParams(chunk_size=1024)
    )
    return root, b"".join(write_car([root], blocks))


def test_a_carv2_is_pinned_and_exported_as_its_carv1_payload(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    root, v1 = a_dag(1)
    blocks = list(CarReader(io.BytesIO(v1)))
    stored = repo_stat(cas_service.url)["NumObjects"]
    v2 = carv2(v1, padding=13, characteristics=bit(0), tail=b"\x80\x08 an index, never read")
    assert dag_import(signed, v2) == [{"Root": {"Cid": {"/": str(root)}, "PinErrorMsg": ""}}]
    assert repo_stat(cas_service.url)["NumObjects"] == stored + len(blocks)
    owners = pin_list(cas_service.url)["Keys"][str(root)]["Owners"]
    assert owners == [signed.identity.address]
    exported = dag_export(cas_service, root)
    reader = CarReader(io.BytesIO(exported))
    assert (reader.version, reader.roots) == (1, [root])
    assert sorted(reader, key=lambda b: b.cid.binary) == sorted(blocks, key=lambda b: b.cid.binary)
    # The same DAG as a CARv1 adds nothing and exports the same bytes.
    with store_unchanged(cas_service):
        assert dag_import(signed, v1) == [{"Root": {"Cid": {"/": str(root)}, "PinErrorMsg": ""}}]
    assert dag_export(cas_service, root) == exported


def test_the_spec_carv2_written_by_go_car_exports_as_its_payload_byte_for_byte(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """go-car wrote it with an index after the payload; kubo's ``dag export`` of its root is
    the payload itself (the same header, the blocks in the same depth-first order)."""
    assert dag_import(signed, SPEC_CARV2_BASIC) == [
        {"Root": {"Cid": {"/": SPEC_CARV2_ROOT}, "PinErrorMsg": ""}}
    ]
    assert SPEC_CARV2_ROOT in pin_list(cas_service.url)["Keys"]
    assert dag_export(cas_service, SPEC_CARV2_ROOT) == SPEC_CARV2_BASIC[51 : 51 + 448]


ROOT, V1 = a_dag(2)
END = 51 + len(V1)


@pytest.mark.parametrize(
    ("car", "message"),
    [
        (carv2(V1)[:40], "truncated CARv2 header: 40 bytes due at byte 11, 29 there"),
        (carv2(V1, offset=40), "CARv2 data offset 40 is inside the pragma and header"),
        (carv2(V1, offset=END + 1), f"CARv2 data offset {END + 1} is beyond the end of the CAR"),
        (carv2(V1, size=len(V1) + 100), f"CARv2 data size {len(V1) + 100} runs past the end"),
        (carv2(V1, size=len(V1) - 1), f"the CARv2 data size ends the payload at byte {END - 1}"),
        (carv2(carv2(V1)), "the CARv2 payload at byte 51 is not a CARv1"),
        (carv2(V1, characteristics=bit(100)), "unknown CARv2 characteristics bits set: 100"),
        (carv2(V1, characteristics=bit(4)), "bit 4 (zero-terminated-payload) is not supported"),
    ],
    ids=[
        "truncated-header",
        "offset-in-header",
        "offset-past-the-end",
        "size-past-the-end",
        "size-cuts-the-last-block",
        "payload-not-carv1",
        "unknown-characteristic",
        "zero-terminated",
    ],
)
def test_a_malformed_carv2_is_invalid_car_and_stores_nothing(
    signed: ServiceClient, cas_service: ServiceProcess, car: bytes, message: str
) -> None:
    """Every block before the fault is verified and staged; the fault discards them all."""
    with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
        dag_import(signed, car)
    assert message in error_of(exc, 400, "invalid_car").message
    assert httpx.post(f"{cas_service.url}/api/v0/block/stat", params={"arg": str(ROOT)}).is_error
