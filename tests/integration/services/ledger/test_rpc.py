"""Standard Ethereum tooling against ``/rpc``: web3.py unchanged, JSON-RPC framing, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest
from eth_account import Account
from web3 import HTTPProvider, Web3

from robocloud.identity import Identity
from robocloud.ledger import Ledger
from tests.integration.services.ledger.conftest import (
    METADATA,
    RobotFactory,
    Service,
    head,
    rpc,
    start_ledger,
)


def test_web3_connects_reads_and_sends(service: Service, robot: RobotFactory) -> None:
    w3 = Web3(HTTPProvider(f"{service.url}/rpc"))
    assert w3.is_connected()
    assert w3.eth.chain_id == 1337
    assert w3.net.version == "1337"
    contracts = httpx.get(f"{service.url}/v1/contracts").json()["contracts"]
    registry = w3.eth.contract(
        address=contracts["Registry"]["address"], abi=contracts["Registry"]["abi"]
    )
    assert service.admin.identity is not None
    assert registry.functions.admin().call() == service.admin.identity.address

    sender = robot(registered=False)
    assert sender.identity is not None
    account = sender.identity.account
    transaction = registry.functions.register(METADATA).build_transaction(
        {"from": account.address, "nonce": w3.eth.get_transaction_count(account.address)}
    )
    signed = account.sign_transaction(transaction)
    tx_hash = w3.eth.send_raw_transaction(signed.raw_transaction)
    receipt = w3.eth.wait_for_transaction_receipt(tx_hash, timeout=10)
    assert receipt["status"] == 1
    assert w3.eth.get_block(receipt["blockNumber"])["hash"] == receipt["blockHash"]
    assert w3.eth.get_transaction(tx_hash)["from"] == account.address
    events = registry.events.RobotRegistered().get_logs(from_block=receipt["blockNumber"])
    assert [e["args"]["robot"] for e in events] == [account.address]
    assert registry.functions.isActive(account.address).call()


def test_batch_and_notifications(service: Service) -> None:
    batch = [
        {"jsonrpc": "2.0", "id": 1, "method": "eth_chainId", "params": []},
        {"jsonrpc": "2.0", "id": 2, "method": "eth_nope", "params": []},
        {"jsonrpc": "2.0", "method": "eth_blockNumber", "params": []},
    ]
    answers = httpx.post(f"{service.url}/rpc", json=batch).json()
    assert answers[0] == {"jsonrpc": "2.0", "id": 1, "result": "0x539"}
    assert answers[1]["error"]["code"] == -32601
    assert len(answers) == 2


@pytest.mark.parametrize(
    ("body", "code"),
    [(b"{not json", -32700), (b"[]", -32600), (b'{"id": 1, "method": "eth_chainId"}', -32600)],
)
def test_framing_errors(service: Service, body: bytes, code: int) -> None:
    answer = httpx.post(
        f"{service.url}/rpc", content=body, headers={"Content-Type": "application/json"}
    ).json()
    assert answer["error"]["code"] == code


def test_malformed_raw_transaction_changes_nothing(service: Service) -> None:
    before = head(service.url)
    answer = rpc(service.url, "eth_sendRawTransaction", ["0x1234"])
    assert answer["error"]["code"] == -32602
    assert answer["error"]["message"].startswith("invalid raw transaction")
    answer = rpc(service.url, "eth_sendRawTransaction", ["not hex"])
    assert answer["error"]["code"] == -32602
    assert head(service.url) == before


def _transfer(identity: Identity, nonce: int, chain_id: int = 1337) -> str:
    transaction = {"chainId": chain_id, "nonce": nonce, "gas": 21_000, "gasPrice": 2 * 10**9}
    transaction |= {"to": identity.address, "value": 1, "data": b""}
    raw = Account.sign_transaction(transaction, identity.account.key).raw_transaction
    return "0x" + bytes(raw).hex()


def _nonce(ledger: Ledger) -> str:
    assert ledger.identity is not None
    answer = rpc(
        ledger.rpc.url.removesuffix("/rpc"),
        "eth_getTransactionCount",
        [ledger.identity.address, "latest"],
    )
    return str(answer["result"])


def test_wrong_chain_id_is_refused(service: Service, robot: RobotFactory) -> None:
    sender = robot(registered=False)
    assert sender.identity is not None
    before = head(service.url)
    answer = rpc(service.url, "eth_sendRawTransaction", [_transfer(sender.identity, 0, 5)])
    assert answer["error"]["code"] == -32000
    assert answer["error"]["message"] == "invalid chain id 5: this chain's id is 1337"
    assert head(service.url) == before
    assert _nonce(sender) == "0x0"


def test_nonce_too_low_is_refused(service: Service, robot: RobotFactory) -> None:
    sender = robot()
    assert sender.identity is not None
    before = head(service.url)
    answer = rpc(service.url, "eth_sendRawTransaction", [_transfer(sender.identity, 0)])
    assert answer["error"]["code"] == -32000
    assert answer["error"]["message"].startswith("nonce too low")
    assert head(service.url) == before
    assert _nonce(sender) == "0x1"


def test_reverted_call_has_code_3_data_and_reason(service: Service, robot: RobotFactory) -> None:
    stranger = robot(registered=False)
    assert stranger.identity is not None
    data = stranger.registry.encode_call("advertise", b"\x01\x55", b"")
    call = {"from": stranger.identity.address, "to": service.admin.addresses.registry}
    call["data"] = "0x" + data.hex()
    for method in ("eth_call", "eth_estimateGas"):
        error = rpc(service.url, method, [call, "latest"])["error"]
        assert error["code"] == 3
        assert error["message"] == "execution reverted: Registry: advertiser is not an active robot"
        assert error["data"].startswith("0x08c379a0")
    assert stranger.advertisement(b"\x01\x55") is None


def test_a_batch_past_its_response_bound_answers_the_rest_response_too_large(
    tmp_path: Path,
) -> None:
    """As geth's --rpc.batch-response-max-size: the calls after the answers pass the bound
    are answered -32003 without being run. 100 eth_getLogs of a 10,000-log block, a 9 KB
    request, answered 142 MB and took the ledger to 650 MB."""
    process = start_ledger(
        tmp_path / "data", {"ROBOCLOUD_LEDGER_RPC_BATCH_RESPONSE_MAX_BYTES": "50000"}
    )
    try:
        single = rpc(process.url, "eth_getBlockByNumber", ["0x1", True])["result"]
        answer = {"jsonrpc": "2.0", "id": 0, "result": single}
        size = len(json.dumps(answer, separators=(",", ":")))
        assert 5_000 < size < 50_000  # the Registry's deployment: its init code is the input
        batch = [
            {"jsonrpc": "2.0", "id": n, "method": "eth_getBlockByNumber", "params": ["0x1", True]}
            for n in range(40)
        ]
        response = httpx.post(f"{process.url}/rpc", json=batch, timeout=30)
        assert len(response.content) < 50_000 + 2 * size
        answers = response.json()
        answered = 50_000 // size + 1
        assert [a["id"] for a in answers] == list(range(40))
        assert all(a["result"] == single for a in answers[:answered])
        too_large = {"code": -32003, "message": "response too large"}
        assert all(a["error"] == too_large for a in answers[answered:])
    finally:
        process.stop()
