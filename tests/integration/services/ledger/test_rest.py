"""REST reads and the faucet: every refusal is the JSON error model and changes nothing."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import anyio
import httpx
import pytest

from robocloud.cid import CID
from robocloud.identity import Identity
from robocloud.ledger import LedgerService
from services.ledger.index import MAX_WAITERS
from tests.integration.services.ledger.conftest import (
    RobotFactory,
    Service,
    faucet,
    head,
    rpc,
    start_ledger,
)
from tests.long_polls import crowd_of_waits

WAITED_FOR = "bafkreihdwdcefgh4dqkjv67uzcmw7ojee6xedzdetojuzjevtenxquvyku"


def _balance(service: Service, address: str) -> int:
    return int(rpc(service.url, "eth_getBalance", [address, "latest"])["result"], 16)


def test_unknown_robot_is_404_naming_it(service: Service) -> None:
    address = Identity.generate().address
    response = httpx.get(f"{service.url}/v1/robots/{address}")
    assert response.status_code == 404
    error = response.json()["error"]
    assert error["code"] == "robot_not_found"
    assert address in error["message"]
    assert error["details"] == {"address": address}


@pytest.mark.parametrize("address", ["0x1234", "robot", "0x" + "zz" * 20])
def test_malformed_address_is_400(service: Service, address: str) -> None:
    response = httpx.get(f"{service.url}/v1/robots/{address}")
    assert response.status_code == 400
    assert response.json()["error"]["code"] == "invalid_address"


def test_malformed_cid_is_400(service: Service) -> None:
    response = httpx.get(f"{service.url}/v1/advertisements", params={"cid": "not-a-cid"})
    assert response.status_code == 400
    assert response.json()["error"]["code"] == "invalid_cid"


def test_latest_block_and_contracts(service: Service) -> None:
    block = head(service.url)
    by_rpc = rpc(service.url, "eth_getBlockByNumber", ["latest", False])["result"]
    assert (hex(block["number"]), block["hash"]) == (by_rpc["number"], by_rpc["hash"])
    contracts = httpx.get(f"{service.url}/v1/contracts").json()
    assert contracts["chain_id"] == 1337
    assert set(contracts["contracts"]) == {"Registry", "AnchorLog"}


def test_faucet_funds_the_signer_once_then_429(service: Service) -> None:
    identity = Identity.generate()
    granted = faucet(service.url, identity)
    assert granted.status_code == 200, granted.text
    receipt = rpc(service.url, "eth_getTransactionReceipt", [granted.json()["tx"]])["result"]
    assert receipt["status"] == "0x1"
    funded = _balance(service, identity.address)
    assert funded == 10**18
    before = head(service.url)
    again = faucet(service.url, identity)
    assert again.status_code == 429
    assert int(again.headers["Retry-After"]) > 3000
    assert again.json()["error"]["code"] == "faucet_rate_limited"
    assert head(service.url) == before
    assert _balance(service, identity.address) == funded


def test_robots_asking_the_faucet_at_once_are_all_funded(service: Service) -> None:
    """Each request read the faucet's pending nonce outside the chain's lock: of 32 at once,
    18 got 500 internal_error ("nonce too low"), and their grants were spent."""
    robots = [Identity.generate() for _ in range(16)]
    with ThreadPoolExecutor(len(robots)) as pool:
        answers = list(pool.map(lambda robot: faucet(service.url, robot), robots))
    assert [answer.status_code for answer in answers] == [200] * len(robots), [
        answer.text for answer in answers if answer.status_code != 200
    ]
    assert len({answer.json()["tx"] for answer in answers}) == len(robots)
    assert {_balance(service, robot.address) for robot in robots} == {10**18}


def test_a_faucet_the_chain_refuses_is_503_and_gives_the_grant_back(tmp_path: Path) -> None:
    """A ChainError had no HTTP answer: 500 internal_error, "see the service log"."""
    process = start_ledger(tmp_path / "data", {"ROBOCLOUD_LEDGER_FAUCET_AMOUNT_WEI": str(10**40)})
    try:
        robot = Identity.generate()
        before = head(process.url)
        for _ in range(2):  # given back: the second try is refused the same, not 429
            refused = faucet(process.url, robot)
            assert refused.status_code == 503, refused.text
            assert refused.headers["Retry-After"] == "1"
            error = refused.json()["error"]
            assert error["code"] == "faucet_failed"
            assert "insufficient funds" in error["message"]
        assert head(process.url) == before
    finally:
        process.stop()


def test_faucet_funds_only_its_signer(service: Service) -> None:
    identity, other = Identity.generate(), Identity.generate()
    response = faucet(service.url, identity, other.address)
    assert response.status_code == 403
    assert response.json()["error"]["code"] == "faucet_signer_mismatch"
    assert _balance(service, other.address) == 0


def test_faucet_needs_a_signature(service: Service) -> None:
    response = httpx.post(f"{service.url}/v1/faucet", json={"address": Identity.generate().address})
    assert response.status_code == 401


@pytest.mark.parametrize(
    ("path", "name"),
    [
        ("/v1/advertisements", "since"),
        ("/v1/advertisements", "after_log_index"),
        ("/v1/anchors", "epoch"),
    ],
)
def test_block_numbers_and_epochs_take_any_uint64(service: Service, path: str, name: str) -> None:
    """Past 2^63 these were 500 (SQLite's integers are signed); any uint64 is a query with
    no answer yet, and a larger number is refused naming the parameter."""
    for value in (2**63, 2**64 - 1):
        response = httpx.get(f"{service.url}{path}", params={name: value})
        assert response.status_code == 200, response.text
        assert list(response.json().values()) == [[]]
    refused = httpx.get(f"{service.url}{path}", params={name: 2**64})
    assert refused.status_code == 422
    assert refused.json()["error"]["details"]["errors"][0]["field"] == f"query.{name}"


@pytest.mark.parametrize("value", ["-1", "first", ""])
def test_a_position_that_is_not_a_log_index_is_refused_naming_it(
    service: Service, value: str
) -> None:
    response = httpx.get(
        f"{service.url}/v1/advertisements", params={"since": 1, "after_log_index": value}
    )
    assert response.status_code == 422, response.text
    assert response.json()["error"]["details"]["errors"][0]["field"] == "query.after_log_index"


def test_a_read_of_advertisements_waits_for_the_next_one(
    service: Service, robot: RobotFactory
) -> None:
    """A follower asked every 2 s and found nothing most of the time (a line in the ledger's
    log each time, forever). With ``wait_s`` the read waits for the block that brings an
    advertisement and answers with it; with none, it answers empty once ``wait_s`` is over."""
    advertiser = robot()
    since = int(head(service.url)["number"]) + 1
    with LedgerService(service.url) as reader, ThreadPoolExecutor(1) as pool:
        waiting = pool.submit(reader.advertisements, since=since, wait_s=25)
        time.sleep(0.5)  # the read is waiting: old ledgers answered it at once, empty
        advertised = advertiser.advertise(CID.decode(WAITED_FOR).binary)
        answer = waiting.result()
        assert [(ad.tx_hash, ad.cid) for ad in answer] == [(advertised.tx_hash, WAITED_FOR)]

        started = time.monotonic()
        assert reader.advertisements(since=advertised.block_number + 1, wait_s=0.5) == []
        assert time.monotonic() - started >= 0.5


@pytest.mark.parametrize("value", ["-1", "25.5", "soon", "nan"])
def test_a_wait_out_of_bounds_is_refused_naming_it(service: Service, value: str) -> None:
    response = httpx.get(f"{service.url}/v1/advertisements", params={"wait_s": value})
    assert response.status_code == 422, response.text
    assert response.json()["error"]["details"]["errors"][0]["field"] == "query.wait_s"
    with LedgerService(service.url) as reader, pytest.raises(ValueError, match="wait_s"):
        reader.advertisements(wait_s=30)


def test_a_waiting_read_is_answered_when_the_ledger_stops(tmp_path: Path) -> None:
    """uvicorn lets the requests in flight finish before the app hears of a stop, 5 s at
    most, then drops them: a waiting read is answered, empty, as soon as the ledger is told
    to stop, and the ledger stops without waiting for it."""
    process = start_ledger(tmp_path / "data")
    try:
        since = int(head(process.url)["number"]) + 1
        with LedgerService(process.url, retries=0) as reader, ThreadPoolExecutor(1) as pool:
            waiting = pool.submit(reader.advertisements, since=since, wait_s=25)
            time.sleep(0.5)
            process.stop()
            assert waiting.result() == []
    finally:
        process.stop()


def test_reads_past_the_waiting_bound_answer_at_once_and_the_ledger_goes_on(
    service: Service, robot: RobotFactory
) -> None:
    """A waiting read holds a connection and nothing else (no thread): past 256 at once, a
    read answers at once as if it had not asked to wait, and the ledger answers other
    requests while they wait."""
    advertiser = robot()
    since = int(head(service.url)["number"]) + 1
    extra = 10

    async def advertise(client: httpx.AsyncClient) -> None:
        latest = await client.get("/v1/blocks/latest")
        assert int(latest.json()["number"]) == since - 1
        await anyio.to_thread.run_sync(advertiser.advertise, CID.decode(WAITED_FOR).binary)

    params = {"since": since, "wait_s": 25}
    crowd = partial(crowd_of_waits, service.url, "/v1/advertisements", params)
    early, woken = anyio.run(crowd, MAX_WAITERS, extra, advertise)
    assert [body["advertisements"] for body in early] == [[]] * extra
    assert len(woken) == MAX_WAITERS
    assert {body["advertisements"][0]["cid"] for body in woken} == {WAITED_FOR}
