"""A small file whose blocks carry megabytes beside its bytes: refused by the read budget,
named, at once, where each read used to hold a worker thread for as long as it hashed.

A leaf of one byte plus junk in a UnixFS field no reader knows, linked 400 times from the
root: 401 block visits for 400 bytes is within two visits per byte, but the read hashed the
junk 400 times (1.6 GB with 4 MiB of it). With 1 M links (an 11 MB CAR) one GET was about
5 hours of CPU, and 45 GETs of a 400-byte file made a 5-byte read wait 19.7 s.
"""

from __future__ import annotations

import httpx
import pytest

from robocloud.client import ServiceClient
from tests.integration.services.cas.test_deep_dags import alive, import_car
from tests.procs import ServiceProcess
from tests.unit.robocloud.test_unixfs import fan, padded_file, padded_leaf

LINKS = 400


@pytest.fixture(scope="module")
def cas_service(shared_cas_service: ServiceProcess) -> ServiceProcess:
    """This module's tests share one cas: none of them needs an empty store."""
    return shared_cas_service


def test_a_file_of_padded_blocks_is_refused_by_the_read_budget_on_every_read_path(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """512 KiB of junk: 200 MiB a read before. Each path stops at the budget (8 MiB and
    100 KiB) before its first MiB is sent, so the answer is a clean 400 naming it."""
    root, blocks = padded_file(512 << 10, LINKS)
    import_car(signed, root, blocks)
    url = f"{cas_service.url}/ipfs/{root}"
    for request, code in (
        (httpx.Request("GET", url), "not_a_file"),
        (httpx.Request("GET", url, headers={"Range": "bytes=10-300"}), "not_a_file"),
        (httpx.Request("POST", f"{cas_service.url}/api/v0/cat?arg={root}"), "not_a_file"),
        (httpx.Request("GET", f"{url}?format=car&entity-bytes=10:*"), "invalid_dag"),
    ):
        with httpx.Client(timeout=60) as client:
            response = client.send(request)
        assert response.status_code == 400, (request.url, response.text[:300])
        error = response.json()["error"]
        assert error["code"] == code
        assert error["details"]["cid"] == str(root)
        assert f"{root} takes more than" in error["message"]
        assert "bytes of blocks for its first" in error["message"]
    assert alive(cas_service)


def test_a_car_of_larger_padded_blocks_is_cut_off_at_the_budget(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """4 MiB of junk: a file read is still 400, while a CAR of a byte range has sent its first
    MiB (the padded block, once) when the budget runs out, so it is cut off as any CAR the
    reader refuses late, not streamed on for 1.6 GB of hashing."""
    root, blocks = padded_file(4 << 20, LINKS)
    import_car(signed, root, blocks)
    url = f"{cas_service.url}/ipfs/{root}"
    response = httpx.get(url, timeout=60)
    assert response.status_code == 400
    assert "bytes of blocks for its first" in response.json()["error"]["message"]
    received: list[bytes] = []

    def read_all(response: httpx.Response) -> None:
        received.extend(response.iter_bytes())

    with httpx.stream("GET", f"{url}?format=car&entity-bytes=10:*", timeout=60) as car:
        assert car.status_code == 200
        with pytest.raises(httpx.RemoteProtocolError):
            read_all(car)
    assert sum(map(len, received)) < 5 << 20
    assert alive(cas_service)


def test_the_same_shape_without_padding_reads(
    signed: ServiceClient, cas_service: ServiceProcess
) -> None:
    """400 links to one honest one-byte leaf: the budget counts bytes, not the repeats."""
    leaf, leaf_block = padded_leaf(0)
    root, root_block = fan(leaf, 1, LINKS)
    import_car(signed, root, {leaf: leaf_block, root: root_block})
    response = httpx.get(f"{cas_service.url}/ipfs/{root}", timeout=60)
    assert response.status_code == 200
    assert response.content == b"!" * LINKS
