"""``Ledger`` and ``robocloud advertise`` against a ledger whose JSON-RPC lies.

Robots sign their own transactions from what the node says (chain id, gas, gas price), so a
lying node must not get a signature for another chain or at a ruinous fee, and what it says
about the transaction afterwards (its hash, its receipt, its events) must be the
transaction's own.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from eth_abi.abi import encode
from eth_utils.crypto import keccak
from typer.testing import CliRunner

from robocloud.cid import CID
from robocloud.cli import app
from robocloud.errors import ConfigurationError, InvalidAnswerError
from robocloud.identity import Identity
from robocloud.ledger import Anchor, ContractAbi, Ledger, LedgerError
from robocloud.ledger.errors import (
    DeploymentMismatchError,
    FeeLimitError,
    TransactionMismatchError,
)
from robocloud.ledger.transactions import MAX_CHAIN_ID, FeeLimits, quantity
from tests.ledger_logs import anchored_log
from tests.scripted_http import Exchange, Reply, ScriptedServer, json_reply, scripted_server

REGISTRY = "0x" + "22" * 20
ANCHOR_LOG = "0x" + "33" * 20
DEPLOYMENT = f"1337:{REGISTRY}"
GWEI = 10**9
CONTENT = CID.from_block(b"hello").binary
REGISTRY_ABI = ContractAbi.load("Registry")
Answers = dict[str, Callable[[list[Any]], Any]]
runner = CliRunner()


def advertised_log(
    robot: str,
    tx_hash: str,
    address: str = REGISTRY,
    *,
    cid_hash: bytes = keccak(CONTENT),
    description: bytes = b"",
) -> dict[str, Any]:
    """The ``Advertised`` event a Registry at ``address`` emits for ``robot``."""
    data = encode(["bytes", "bytes", "bool", "uint64"], [CONTENT, description, True, 1_700_000_000])
    return {
        "address": address,
        "topics": [
            "0x" + REGISTRY_ABI.event_topic("Advertised").hex(),
            "0x" + cid_hash.hex(),
            "0x" + "00" * 12 + robot[2:].lower(),
        ],
        "data": "0x" + data.hex(),
        "blockNumber": "0x5",
        "transactionHash": tx_hash,
        "logIndex": "0x0",
    }


def honest(robot: str) -> Answers:
    """What a truthful development node answers to an ``advertise``."""

    def receipt(params: list[Any]) -> dict[str, Any]:
        return {
            "transactionHash": params[0],
            "blockNumber": "0x5",
            "blockHash": "0x" + "cd" * 32,
            "status": "0x1",
            "gasUsed": "0x5208",
            "logs": [advertised_log(robot, params[0])],
        }

    return {
        "eth_chainId": lambda _: hex(1337),
        "eth_estimateGas": lambda _: hex(100_000),
        "eth_gasPrice": lambda _: hex(2 * GWEI),
        "eth_getTransactionCount": lambda _: "0x0",
        "eth_sendRawTransaction": lambda params: "0x" + keccak(hexstr=params[0]).hex(),
        "eth_getTransactionReceipt": receipt,
    }


def ledger_script(answers: Answers) -> Callable[[Exchange], Reply]:
    """The ledger service's ``/v1/contracts`` and a JSON-RPC node answering ``answers``."""

    def script(exchange: Exchange) -> Reply:
        if exchange.path == "/v1/contracts":
            contracts = {"Registry": {"address": REGISTRY}, "AnchorLog": {"address": ANCHOR_LOG}}
            return json_reply(json.dumps({"contracts": contracts}))
        call = json.loads(exchange.body)
        result = answers[call["method"]](call["params"])
        return json_reply(json.dumps({"jsonrpc": "2.0", "id": call["id"], "result": result}))

    return script


@contextmanager
def lying_ledger(robot: Identity, **lies: Callable[[list[Any]], Any]) -> Iterator[ScriptedServer]:
    with scripted_server(ledger_script({**honest(robot.address), **lies})) as server:
        yield server


def methods(server: ScriptedServer) -> list[str]:
    return [json.loads(e.body)["method"] for e in server.exchanges if e.path == "/rpc"]


def raw_sent(server: ScriptedServer) -> str:
    (raw,) = [
        json.loads(e.body)["params"][0]
        for e in server.exchanges
        if e.path == "/rpc" and json.loads(e.body)["method"] == "eth_sendRawTransaction"
    ]
    return str(raw)


def test_an_honest_node_gets_the_advertisement_signed() -> None:
    robot = Identity.generate()
    with lying_ledger(robot) as server, Ledger.connect(server.url, robot) as ledger:
        event = ledger.advertise(CONTENT)
    assert event.tx_hash == "0x" + keccak(hexstr=raw_sent(server)).hex()


@pytest.mark.parametrize(
    ("lie", "limit"),
    [
        ({"eth_gasPrice": lambda _: hex(5000 * GWEI)}, "ROBOCLOUD_MAX_FEE_PER_GAS_GWEI"),
        ({"eth_estimateGas": lambda _: hex(30_000_000)}, "ROBOCLOUD_MAX_GAS"),
    ],
    ids=["gas-price", "gas"],
)
def test_a_fee_over_the_limits_is_refused_before_anything_is_signed(
    lie: Answers, limit: str
) -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot, **lie) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(FeeLimitError, match=limit),
    ):
        ledger.advertise(CONTENT)
    assert "eth_sendRawTransaction" not in methods(server)


def test_the_fee_limits_are_the_robots_to_raise(monkeypatch: pytest.MonkeyPatch) -> None:
    robot = Identity.generate()
    lies: Answers = {
        "eth_gasPrice": lambda _: hex(5000 * GWEI),
        "eth_estimateGas": lambda _: hex(30_000_000),
    }
    monkeypatch.setenv("ROBOCLOUD_MAX_GAS", "40000000")
    monkeypatch.setenv("ROBOCLOUD_MAX_FEE_PER_GAS_GWEI", "5000")
    with lying_ledger(robot, **lies) as server, Ledger.connect(server.url, robot) as ledger:
        ledger.advertise(CONTENT)
    limits = FeeLimits(max_gas=40_000_000, max_fee_per_gas=4999 * GWEI)
    with (
        lying_ledger(robot, **lies) as server,
        Ledger.connect(server.url, robot, fee_limits=limits) as ledger,
        pytest.raises(FeeLimitError, match="at most 4999 gwei"),
    ):
        ledger.advertise(CONTENT)


@pytest.mark.parametrize(
    ("name", "value"),
    [("ROBOCLOUD_MAX_GAS", "lots"), ("ROBOCLOUD_MAX_FEE_PER_GAS_GWEI", "-1")],
)
def test_an_unusable_fee_limit_is_a_configuration_error(
    monkeypatch: pytest.MonkeyPatch, name: str, value: str
) -> None:
    monkeypatch.setenv(name, value)
    with pytest.raises(ConfigurationError, match=name):
        FeeLimits.from_env()


def test_a_node_of_another_chain_gets_no_signature(monkeypatch: pytest.MonkeyPatch) -> None:
    robot = Identity.generate()
    monkeypatch.setenv("ROBOCLOUD_EXPECTED_DEPLOYMENT", DEPLOYMENT)
    with (
        lying_ledger(robot, eth_chainId=lambda _: "0x1") as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        with pytest.raises(DeploymentMismatchError, match=r"serves chain 1, .* on chain 1337"):
            ledger.advertise(CONTENT)
        with pytest.raises(DeploymentMismatchError):
            _ = ledger.chain_id
    assert "eth_sendRawTransaction" not in methods(server)


def test_the_chain_of_the_deployment_named_is_signed_for() -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot) as server,
        Ledger.connect(server.url, robot, deployment=DEPLOYMENT) as ledger,
    ):
        ledger.advertise(CONTENT)
        assert ledger.chain_id == 1337


def test_a_ledger_naming_another_registry_is_refused() -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot) as server,
        pytest.raises(DeploymentMismatchError, match="Registry"),
    ):
        Ledger.connect(server.url, robot, deployment=f"1337:0x{'44' * 20}")


def test_a_hash_answered_for_another_transaction_is_refused() -> None:
    robot = Identity.generate()
    other = "0x" + "ab" * 32
    with (
        lying_ledger(robot, eth_sendRawTransaction=lambda _: other) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(TransactionMismatchError) as err,
    ):
        ledger.advertise(CONTENT)
    assert isinstance(err.value, InvalidAnswerError)
    assert err.value.tx_hash == "0x" + keccak(hexstr=raw_sent(server)).hex()
    assert "eth_getTransactionReceipt" not in methods(server)


def test_a_receipt_of_another_transaction_is_refused() -> None:
    robot = Identity.generate()
    other = "0x" + "ab" * 32

    def receipt(params: list[Any]) -> dict[str, Any]:
        return {
            **honest(robot.address)["eth_getTransactionReceipt"](params),
            "transactionHash": other,
        }

    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(TransactionMismatchError, match="receipt"),
    ):
        ledger.advertise(CONTENT)


@pytest.mark.parametrize("where", ["address", "transaction"])
def test_an_event_from_elsewhere_is_not_the_registrys(where: str) -> None:
    robot = Identity.generate()

    def receipt(params: list[Any]) -> dict[str, Any]:
        if where == "address":
            log = advertised_log(robot.address, params[0], address="0x" + "44" * 20)
        else:
            log = advertised_log(robot.address, "0x" + "ab" * 32)
        return {**honest(robot.address)["eth_getTransactionReceipt"](params), "logs": [log]}

    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(LedgerError, match="emitted no Advertised event"),
    ):
        ledger.advertise(CONTENT)


def test_the_cli_refuses_a_ruinous_fee_in_one_line(keystore: Path) -> None:
    robot = Identity.load(keystore, "pw")
    with lying_ledger(robot, eth_gasPrice=lambda _: hex(5000 * GWEI)) as server:
        result = runner.invoke(
            app,
            [
                "advertise",
                str(CID.from_bytes(CONTENT)),
                "--keystore",
                str(keystore),
                "--ledger",
                server.url,
            ],
        )
    assert result.exit_code == 1, result.output
    assert result.stderr.startswith("error: refused to sign at the node's gas price of 5000 gwei")
    assert "ROBOCLOUD_MAX_FEE_PER_GAS_GWEI" in result.stderr
    assert "eth_sendRawTransaction" not in methods(server)


@pytest.mark.parametrize(
    "value", ["0xzz", None, 5, "0x", "539", "0x" + "f" * 65, "0x1_0", " 0x1"], ids=repr
)
def test_a_malformed_quantity_is_an_invalid_answer(value: Any) -> None:
    with pytest.raises(InvalidAnswerError, match="where a quantity belongs"):
        quantity(value)


def test_a_quantity_is_read_as_hex() -> None:
    assert [quantity("0x0"), quantity("0x539"), quantity("0x" + "f" * 64)] == [0, 1337, 2**256 - 1]


@pytest.mark.parametrize(
    "receipt",
    [{}, {"transactionHash": "0x", "blockNumber": "0xnope"}, "receipt", {"logs": "x"}],
    ids=["empty", "bad-quantity", "not-an-object", "logs-not-a-list"],
)
def test_a_malformed_receipt_names_the_transaction_sent(receipt: Any) -> None:
    robot = Identity.generate()

    def answer(params: list[Any]) -> Any:
        if isinstance(receipt, dict) and "logs" in receipt:
            return {**honest(robot.address)["eth_getTransactionReceipt"](params), **receipt}
        return receipt

    with (
        lying_ledger(robot, eth_getTransactionReceipt=answer) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(TransactionMismatchError, match="receipt for 0x") as err,
    ):
        ledger.advertise(CONTENT)
    assert err.value.tx_hash == "0x" + keccak(hexstr=raw_sent(server)).hex()


def test_a_malformed_log_is_an_invalid_answer() -> None:
    robot = Identity.generate()

    def receipt(params: list[Any]) -> dict[str, Any]:
        log = {**advertised_log(robot.address, params[0]), "data": "0x1234"}
        return {**honest(robot.address)["eth_getTransactionReceipt"](params), "logs": [log]}

    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match="malformed log of Registry"),
    ):
        ledger.advertise(CONTENT)


@pytest.mark.parametrize("result", ["0x", None, "zz", "0x" + "00" * 31 + "07"], ids=repr)
def test_a_call_result_that_is_not_the_functions_is_an_invalid_answer(result: Any) -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot, eth_call=lambda _: result) as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        with pytest.raises(InvalidAnswerError):
            ledger.registration_mode()
        with pytest.raises(InvalidAnswerError):
            ledger.advertisement(CONTENT)


def test_logs_that_are_not_a_list_are_an_invalid_answer() -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot, eth_getLogs=lambda _: "logs") as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match="eth_getLogs"),
    ):
        ledger.advertisements()


@pytest.mark.parametrize("chain_id", ['"0xzz"', "null"])
def test_verify_ends_in_one_line_on_a_malformed_chain_id(chain_id: str) -> None:
    def script(exchange: Exchange) -> Reply:
        if exchange.path.startswith("/v1/records/"):
            return json_reply(b'{"whatever": 1}')
        call = json.loads(exchange.body)
        return json_reply(f'{{"jsonrpc":"2.0","id":{call["id"]},"result":{chain_id}}}')

    with scripted_server(script) as server:
        rpc = f"{server.url}/rpc"
        command = ["verify", "imu-1-0", "--storage", server.url, "--rpc", rpc]
        result = runner.invoke(app, [*command, "--anchor-log", ANCHOR_LOG])
    assert result.exit_code == 6, result.output
    assert result.stderr.startswith("error: the node sent")
    assert result.stderr.count("\n") == 1


def receipt_with(robot: Identity, **changes: Any) -> Callable[[list[Any]], Any]:
    """The honest receipt of the transaction sent, its log changed by ``changes``."""

    def receipt(params: list[Any]) -> dict[str, Any]:
        honest_receipt = honest(robot.address)["eth_getTransactionReceipt"](params)
        log = {**advertised_log(robot.address, params[0]), **changes.pop("log", {})}
        return {**honest_receipt, "logs": [log], **changes}

    return receipt


@pytest.mark.parametrize(
    ("changes", "error", "message"),
    [
        ({"log": {"topics": None}}, InvalidAnswerError, "advertiser differ"),
        ({"log": {"blockNumber": "0x6"}}, InvalidAnswerError, "block differ"),
        ({"log": {"blockNumber": "-5"}}, InvalidAnswerError, "malformed log of Registry"),
        ({"log": {"blockNumber": "0x" + "f" * 17}}, InvalidAnswerError, "malformed log"),
        ({"log": {"blockNumber": hex(2**63)}}, InvalidAnswerError, r"malformed log.*past 2\^63"),
        (
            {"blockNumber": hex(2**63), "log": {"blockNumber": hex(2**63)}},
            TransactionMismatchError,
            r"receipt for 0x.*block 9223372036854775808, past 2\^63 - 1",
        ),
        ({"status": "0x2"}, TransactionMismatchError, "receipt for 0x"),
        ({"log": {"transactionHash": "0x" + "ab" * 31}}, InvalidAnswerError, "32-byte hash"),
        ({"log": {"transactionHash": None}}, InvalidAnswerError, "malformed log of Registry"),
        ({"blockHash": "0xcd"}, TransactionMismatchError, "receipt for 0x.*32-byte hash"),
        ({"blockHash": "0x" + "zz" * 32}, TransactionMismatchError, "receipt for 0x"),
    ],
    ids=[
        "another-advertiser",
        "another-block",
        "negative-block",
        "huge-block",
        "log-block-past-int64",
        "receipt-block-past-int64",
        "status-2",
        "log-tx-hash-short",
        "log-tx-hash-null",
        "receipt-block-hash-short",
        "receipt-block-hash-not-hex",
    ],
)
def test_an_event_or_receipt_the_node_invents_is_not_the_transactions(
    changes: dict[str, Any], error: type[Exception], message: str
) -> None:
    """The event's arguments, its block and the receipt's status were the node's word: a
    robot was told of another robot's advertisement, block -5, or success for status 2; a
    block past 2^63 - 1 was taken, which a storage node then failed to record (OverflowError)."""
    robot = Identity.generate()
    if changes.get("log", {}).get("topics", 1) is None:
        changes["log"]["topics"] = advertised_log(Identity.generate().address, "0x")["topics"]
    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt_with(robot, **changes)) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(error, match=message),
    ):
        ledger.advertise(CONTENT)


def test_a_nonce_past_eip_2681_is_refused_before_signing() -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot, eth_getTransactionCount=lambda _: hex(2**64 - 1)) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match="EIP-2681"),
    ):
        ledger.advertise(CONTENT)
    assert "eth_sendRawTransaction" not in methods(server)


@pytest.mark.parametrize(
    ("log_changes", "message"),
    [
        ({"topics": None}, "log whose advertiser differ from the filter's"),
        ({"blockNumber": "0x1"}, "outside the filter's blocks 3 to latest"),
    ],
    ids=["another-advertiser", "before-from-block"],
)
def test_logs_the_filter_did_not_ask_for_are_refused(
    log_changes: dict[str, Any], message: str
) -> None:
    """A storage node recovering from a crash took another node's anchor, of an older
    block, for its own: the node's logs were checked for their contract only."""
    robot = Identity.generate()
    if log_changes.get("topics", 1) is None:
        log_changes["topics"] = advertised_log(Identity.generate().address, "0x")["topics"]
    log = {**advertised_log(robot.address, "0x" + "ab" * 32), **log_changes}
    with (
        lying_ledger(robot, eth_getLogs=lambda _: [log]) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match=message),
    ):
        ledger.advertisements(advertiser=robot.address, from_block=3)


def test_the_chain_id_a_robot_reports_is_the_one_it_signed_for() -> None:
    """A storage node asked eth_chainId again after anchoring and published the answer
    (chain 1) beside an anchor signed for chain 1337: every proof of that epoch then failed."""
    robot = Identity.generate()
    answers = iter([hex(1337), hex(1), hex(1)])
    with (
        lying_ledger(robot, eth_chainId=lambda _: next(answers)) as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        ledger.advertise(CONTENT)
        assert ledger.chain_id == 1337


@pytest.mark.parametrize("chain_id", [2**64, 2**63, MAX_CHAIN_ID + 1], ids=hex)
def test_a_chain_id_past_eip_2294_is_refused_before_signing(chain_id: int) -> None:
    """A chain id up to 2^64 - 1 was signed for: past 2^63 the storage node sent its anchor,
    then raised OverflowError recording it, at every retry."""
    robot = Identity.generate()
    with (
        lying_ledger(robot, eth_chainId=lambda _: hex(chain_id)) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match="EIP-2294"),
    ):
        ledger.advertise(CONTENT)
    assert "eth_sendRawTransaction" not in methods(server)


ROOT = b"\xaa" * 32
OTHER_NODE = "0x" + "44" * 20
ANCHOR = Anchor(REGISTRY, 1, ROOT, 3, 1_700_000_000, 9, "0x" + "ab" * 32)
"""The anchor asked for below: ``REGISTRY`` stands for a storage node, anchoring epoch 1."""


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"node": OTHER_NODE}, "log whose node differ"),
        ({"epoch": 77}, "log whose epoch differ"),
        ({"node": OTHER_NODE, "epoch": 77}, "log whose node, epoch differ"),
        ({"block_number": 8}, "of block 8, outside the filter's blocks 9 to 9"),
        ({"block_number": 10}, "of block 10, outside the filter's blocks 9 to 9"),
    ],
    ids=["another-node", "another-epoch", "both", "before-from-block", "after-to-block"],
)
def test_anchors_the_filter_did_not_ask_for_are_refused_naming_what_differs(
    changes: dict[str, Any], message: str
) -> None:
    """The node's word on which anchors match was taken: another node's anchor of epoch 77,
    at a block before fromBlock, came back as the one asked for."""
    robot = Identity.generate()
    log = anchored_log(ANCHOR_LOG, replace(ANCHOR, **changes))
    with (
        lying_ledger(robot, eth_getLogs=lambda _: [log]) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match=message),
    ):
        ledger.anchors(node=REGISTRY, epoch=1, from_block=9, to_block=9)


@pytest.mark.parametrize(
    "tx_hash",
    ["0x" + "ab" * 31, "0x" + "ab" * 33, "ab" * 32, "0x" + "zz" * 32, "0x" + "ab" * 4096, 7],
    ids=["short", "long", "no-0x", "not-hex", "8-KiB", "a-number"],
)
def test_an_anchor_whose_transaction_is_not_a_hash_is_refused(tx_hash: Any) -> None:
    """A log's ``transactionHash`` was ``str()`` of whatever the node sent: a storage node
    recovering from a crash recorded it and published it as its anchor's transaction."""
    robot = Identity.generate()
    log = {**anchored_log(ANCHOR_LOG, ANCHOR), "transactionHash": tx_hash}
    with (
        lying_ledger(robot, eth_getLogs=lambda _: [log]) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match="malformed log of AnchorLog") as err,
    ):
        ledger.anchors(node=REGISTRY, epoch=1, from_block=9, to_block=9)
    assert len(str(err.value)) < 400


def test_a_transaction_hash_is_read_in_lower_case() -> None:
    """The hash a robot computes for its own transaction is lower-case hex: an anchor's
    transaction read back from a node is written the same way, whatever case it used."""
    robot = Identity.generate()
    log = {**anchored_log(ANCHOR_LOG, ANCHOR), "transactionHash": "0x" + "AB" * 32}
    with (
        lying_ledger(robot, eth_getLogs=lambda _: [log]) as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        (anchor,) = ledger.anchors(node=REGISTRY, epoch=1, from_block=9, to_block=9)
    assert anchor == ANCHOR


def test_anchors_asks_for_the_blocks_it_names() -> None:
    robot = Identity.generate()
    queries: list[Any] = []

    def logs(params: list[Any]) -> list[Any]:
        queries.append(params[0])
        return [anchored_log(ANCHOR_LOG, ANCHOR)]

    with (
        lying_ledger(robot, eth_getLogs=logs) as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        (anchor,) = ledger.anchors(node=REGISTRY, epoch=1, from_block=9, to_block=9)
        ledger.anchors(node=REGISTRY)
    assert anchor == ANCHOR
    assert [(q["fromBlock"], q["toBlock"]) for q in queries] == [("0x9", "0x9"), ("0x0", "latest")]


def test_the_highest_chain_id_eip_2294_allows_is_signed_for() -> None:
    robot = Identity.generate()
    with (
        lying_ledger(robot, eth_chainId=lambda _: hex(MAX_CHAIN_ID)) as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        ledger.advertise(CONTENT)
        assert ledger.chain_id == MAX_CHAIN_ID == 2**63 - 37


@pytest.mark.parametrize(
    ("log", "message"),
    [
        ({"cid_hash": keccak(b"another")}, "cidHash differ"),
        ({"description": CONTENT}, "descriptionCid differ"),
    ],
    ids=["another-cid-hash", "another-description"],
)
def test_an_advertisement_event_must_carry_what_was_sent(log: dict[str, Any], message: str) -> None:
    """The indexed CID hash and the description CID were the node's word: the robot was told
    its advertisement described content it never named."""
    robot = Identity.generate()

    def receipt(params: list[Any]) -> dict[str, Any]:
        honest_receipt = honest(robot.address)["eth_getTransactionReceipt"](params)
        return {**honest_receipt, "logs": [advertised_log(robot.address, params[0], **log)]}

    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match=message),
    ):
        ledger.advertise(CONTENT)


def anchor_receipt(node: str, epoch: int, block: int) -> Callable[[list[Any]], Any]:
    """A receipt of block 5 whose one log is ``node``'s Anchored event of ``epoch``."""

    def receipt(params: list[Any]) -> dict[str, Any]:
        mined = honest(node)["eth_getTransactionReceipt"](params)
        anchor = replace(ANCHOR, node=node, epoch=epoch, block_number=block, tx_hash=params[0])
        return {**mined, "logs": [anchored_log(ANCHOR_LOG, anchor)]}

    return receipt


def test_a_robots_anchor_is_the_event_of_its_transaction() -> None:
    robot = Identity.generate()
    receipt = anchor_receipt(robot.address, 1, 5)
    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt) as server,
        Ledger.connect(server.url, robot) as ledger,
    ):
        anchor = ledger.anchor(1, ROOT, 3)
    assert (anchor.node, anchor.epoch, anchor.block_number) == (robot.address, 1, 5)


@pytest.mark.parametrize(
    ("event", "message"),
    [(("0x" + "33" * 20, 999, 5), "node, epoch differ"), ((None, 1, 6), "block differ")],
    ids=["another-node-and-epoch", "another-block"],
)
def test_an_anchor_event_the_node_invents_is_not_the_transactions(
    event: tuple[str | None, int, int], message: str
) -> None:
    """anchor(1, 0xaa..., 3) returned Anchor(node=0x3333..., epoch=999, block_number=-5)."""
    robot = Identity.generate()
    node, epoch, block = event
    receipt = anchor_receipt(node or robot.address, epoch, block)
    with (
        lying_ledger(robot, eth_getTransactionReceipt=receipt) as server,
        Ledger.connect(server.url, robot) as ledger,
        pytest.raises(InvalidAnswerError, match=message),
    ):
        ledger.anchor(1, ROOT, 3)
