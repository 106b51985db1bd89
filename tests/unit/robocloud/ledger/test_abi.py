"""ABI encoding, event decoding and revert decoding of the SDK's ledger client."""

from __future__ import annotations

import pytest
from eth_abi.abi import decode, encode
from eth_utils.crypto import keccak

from robocloud.ledger.abi import ERROR_SELECTOR, PANIC_SELECTOR, ContractAbi, decode_revert
from robocloud.ledger.errors import RevertError, RpcError

ADDRESS = "0x5B38Da6a701c568545dCfcB03FcB875f56beddC4"


def test_shipped_abis_load() -> None:
    registry = ContractAbi.load("Registry")
    anchor_log = ContractAbi.load("AnchorLog")
    assert {"register", "advertise", "getRobot", "grantRole"} <= registry.functions.keys()
    assert {"anchor", "rootAt", "anchorAt", "latest"} <= anchor_log.functions.keys()
    assert "Advertised" in registry.events
    assert "Anchored" in anchor_log.events


def test_unknown_contract_or_function_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="no ABI for contract 'Nope'"):
        ContractAbi.load("Nope")
    with pytest.raises(ValueError, match="Registry has no function 'nope'"):
        ContractAbi.load("Registry").encode_call("nope")
    with pytest.raises(TypeError, match=r"takes 2 arguments, not 1"):
        ContractAbi.load("Registry").encode_call("advertise", b"\x01")


def test_overloaded_functions_are_refused() -> None:
    entry = {"type": "function", "name": "f", "inputs": [], "outputs": []}
    overloaded = {**entry, "inputs": [{"name": "x", "type": "uint256"}]}
    with pytest.raises(ValueError, match="overloaded"):
        ContractAbi("C", [entry, overloaded])


def test_encode_call_is_selector_plus_abi_encoding() -> None:
    data = ContractAbi.load("Registry").encode_call("advertise", b"\x01\x55", b"")
    assert data[:4] == keccak(text="advertise(bytes,bytes)")[:4]
    assert decode(["bytes", "bytes"], data[4:]) == (b"\x01\x55", b"")


def test_decode_output_checksums_addresses() -> None:
    registry = ContractAbi.load("Registry")
    raw = encode(
        ["address", "uint64", "uint64", "uint32", "bytes"], [ADDRESS.lower(), 7, 8, 2, b"d"]
    )
    assert registry.decode_output("getAdvertisement", raw) == (ADDRESS, 7, 8, 2, b"d")


def test_decode_log_reads_topics_and_data() -> None:
    registry = ContractAbi.load("Registry")
    cid = b"\x01\x55\x12\x20" + bytes(32)
    log = {
        "address": ADDRESS.lower(),
        "topics": [
            "0x" + registry.event_topic("Advertised").hex(),
            "0x" + keccak(cid).hex(),
            "0x" + "00" * 12 + ADDRESS[2:].lower(),
        ],
        "data": "0x" + encode(["bytes", "bytes", "bool", "uint64"], [cid, b"", True, 99]).hex(),
        "blockNumber": "0x10",
        "transactionHash": "0x" + "ab" * 32,
        "logIndex": "0x2",
    }
    decoded = registry.decode_log(log)
    assert decoded is not None
    assert decoded.event == "Advertised"
    assert decoded.args == {
        "cidHash": keccak(cid),
        "advertiser": ADDRESS,
        "cid": cid,
        "descriptionCid": b"",
        "first": True,
        "timestamp": 99,
    }
    assert (decoded.address, decoded.block_number, decoded.log_index) == (ADDRESS, 16, 2)
    assert ContractAbi.load("AnchorLog").decode_log(log) is None
    assert registry.decode_log({**log, "topics": []}) is None


def test_a_revert_reason_that_is_not_utf8_is_shown_as_hex() -> None:
    """eth_abi raises UnicodeDecodeError, not DecodingError, for such a string: it escaped
    as a traceback from every CLI command that reads the chain."""
    data = ERROR_SELECTOR + encode(["bytes"], [b"\xff\xfe"])
    assert decode_revert(data) == f"execution reverted with undecodable data 0x{data.hex()}"


def test_decode_revert_reasons() -> None:
    assert decode_revert(ERROR_SELECTOR + encode(["string"], ["Registry: empty CID"])) == (
        "Registry: empty CID"
    )
    assert decode_revert(PANIC_SELECTOR + encode(["uint256"], [0x11])) == (
        "panic 0x11: arithmetic overflow or underflow"
    )
    assert decode_revert(b"") == "execution reverted without a reason"
    assert decode_revert(b"\xde\xad") == "execution reverted with undecodable data 0xdead"
    truncated = ERROR_SELECTOR + b"\x00" * 3
    assert decode_revert(truncated).startswith("execution reverted with undecodable data")


def test_decode_revert_custom_errors_from_an_abi() -> None:
    error = {"type": "error", "name": "TooLate", "inputs": [{"name": "d", "type": "uint64"}]}
    contract = ContractAbi("Broker", [error])
    data = keccak(text="TooLate(uint64)")[:4] + encode(["uint64"], [5])
    assert decode_revert(data, [contract]) == "TooLate(5)"
    assert decode_revert(data).startswith("execution reverted with undecodable data")


@pytest.mark.parametrize(
    ("offset", "length"),
    [(32, 2**256 - 1), (2**256 - 1, 5), (2**64, 5), (32, 2**64)],
    ids=["length-2^256-1", "offset-2^256-1", "offset-2^64", "length-2^64"],
)
def test_an_error_string_with_a_hostile_offset_or_length_is_shown_as_hex(
    offset: int, length: int
) -> None:
    """eth_abi raised OverflowError on a length or offset word past what a seek takes, which
    escaped from register, is_active and estimate_gas as a traceback."""
    data = ERROR_SELECTOR + offset.to_bytes(32, "big") + length.to_bytes(32, "big") + b"ab"
    assert decode_revert(data) == f"execution reverted with undecodable data 0x{data.hex()}"


def test_megabytes_from_a_node_are_not_kept_whole_in_an_error() -> None:
    """The storage node kept a 40-million-character error as its anchorer's last error,
    logged it and served it on /v1/node."""
    data = b"\x01\x02\x03\x04" + b"\xee" * (20 << 20)
    shown = decode_revert(data)
    assert len(shown) < 2_000
    assert shown.endswith(f"({len(data)} bytes)")
    error = RpcError("eth_call", -32000, "x" * (30 << 20))
    assert len(str(error)) < 2_000
    assert f"({30 << 20} characters)" in str(error)
    assert len(error.message) == 30 << 20
    assert len(str(RevertError("y" * (1 << 20)))) < 2_000
