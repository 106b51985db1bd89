"""Each failure's exit code and hint: what a script or an operator does next."""

from __future__ import annotations

import pytest

from robocloud.cas import LocalContentError, NotAFileError
from robocloud.cid import CID
from robocloud.cli.exits import ExitCode, failure_of
from robocloud.errors import (
    ApiError,
    ConfigurationError,
    ConnectError,
    FormatError,
    InvalidAnswerError,
    KeystoreError,
    TransportTimeoutError,
    error_class_for,
)
from robocloud.ledger.errors import RevertError, RpcError, TransactionTimeoutError

ROOT = CID.from_block(b"a directory, say")


def api(status: int, code: str = "some_code", **details: object) -> ApiError:
    return error_class_for(status)(status, code, "message", dict(details), "req-1")


@pytest.mark.parametrize(
    ("error", "code", "hint"),
    [
        (
            ConnectError("cannot connect", method="GET", url="http://x/y", service="cas"),
            ExitCode.UNREACHABLE,
            "ROBOCLOUD_CAS_URL or --cas",
        ),
        (
            TransportTimeoutError("timed out", method="GET", url="http://x/y", service=None),
            ExitCode.UNREACHABLE,
            "retry",
        ),
        (api(403, "address_not_allowed"), ExitCode.REFUSED, "robocloud register"),
        (api(401, "stale_timestamp"), ExitCode.REFUSED, "clock"),
        (api(404), ExitCode.REFUSED, None),
        (api(429, retry_after="3"), ExitCode.UNAVAILABLE, "try again in 3 s"),
        (api(500), ExitCode.UNAVAILABLE, "request id"),
        (api(503), ExitCode.UNAVAILABLE, "request id"),
        (api(507, "insufficient_storage"), ExitCode.UNAVAILABLE, "operator frees space"),
        (api(507, "quota_exceeded"), ExitCode.REFUSED, "robocloud unpin CID"),
        (api(429, "write_rate_exceeded", retry_after=600), ExitCode.UNAVAILABLE, "in 600 s"),
        (
            RpcError("eth_sendRawTransaction", -32000, "insufficient funds"),
            ExitCode.REFUSED,
            "faucet",
        ),
        (
            RevertError("Registry: advertiser is not an active robot"),
            ExitCode.REFUSED,
            "robocloud register",
        ),
        (api(403, "registration_pending"), ExitCode.REFUSED, "robocloud admin pending"),
        (api(403, "robot_inactive"), ExitCode.REFUSED, "robocloud admin reinstate"),
        (RevertError("Registry: caller is not the admin"), ExitCode.REFUSED, "admin.json"),
        (
            RevertError("Registry: caller is not a registrar"),
            ExitCode.REFUSED,
            "registrar role",
        ),
        (
            RevertError("Registry: no pending registration"),
            ExitCode.REFUSED,
            "robocloud admin pending",
        ),
        (RevertError("Registry: account is not registered"), ExitCode.REFUSED, "robocloud robot"),
        (RevertError("Registry: CID too long"), ExitCode.REFUSED, None),
        (TransactionTimeoutError("0xab", 60), ExitCode.UNAVAILABLE, "mined"),
        (InvalidAnswerError("bad"), ExitCode.INVALID_ANSWER, "nothing was written"),
        (FormatError("bad CAR"), ExitCode.INVALID_ANSWER, "nothing was written"),
        (ConfigurationError("bad url"), ExitCode.USAGE, "ROBOCLOUD_*_URL"),
        (KeystoreError("no keystore"), ExitCode.ERROR, None),
        (NotAFileError(ROOT, "a symbolic link"), ExitCode.USAGE, "files and directories only"),
        (LocalContentError("d/link is a symbolic link"), ExitCode.ERROR, None),
        (PermissionError(13, "Permission denied"), ExitCode.ERROR, None),
        (KeyboardInterrupt(), ExitCode.INTERRUPTED, None),
    ],
    ids=lambda value: type(value).__name__ if isinstance(value, BaseException) else None,
)
def test_failures_map_to_exit_codes_and_hints(
    error: BaseException, code: ExitCode, hint: str | None
) -> None:
    failure = failure_of(error)
    assert failure.code == code
    if hint is None:
        assert failure.hint is None
    else:
        assert failure.hint is not None
        assert hint in failure.hint


def test_an_api_error_message_carries_status_code_and_request_id() -> None:
    assert failure_of(api(404, "block_not_found")).message == (
        "404 block_not_found: message (request id req-1)"
    )
