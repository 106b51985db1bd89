"""How the CLI fails: one line on stderr with a hint, and an exit code that says what to do.

Every SDK error is a ``RobocloudError``, so the CLI catches that once (in ``main``), plus
``OSError`` for local files. The exit codes group failures by what a script or a robot should
do next: fix the command (2), retry later (3, 5), stop trusting that service (6), or fix
something locally (1, 4). ``robocloud --help`` lists them from ``MEANINGS``, and a test
keeps ``docs/cli.md`` in step.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING

from rich.text import Text

from robocloud.cas import LocalContentError, NoSuchPathError, NotAFileError
from robocloud.cli.output import console, untrusted
from robocloud.client import RedirectError
from robocloud.errors import (
    ApiError,
    ConfigurationError,
    FormatError,
    InvalidAnswerError,
    RateLimitedError,
    ServerError,
    TransportError,
    TransportTimeoutError,
)

if TYPE_CHECKING:
    from robocloud.ledger.errors import RevertError, RpcError

MAX_MESSAGE = 400
"""Characters of a message printed; a hostile service may answer a megabyte of text."""


class ExitCode(IntEnum):
    """The ``robocloud`` command's exit status; ``MEANINGS`` says what each one means."""

    OK = 0
    ERROR = 1
    USAGE = 2
    UNREACHABLE = 3
    REFUSED = 4
    UNAVAILABLE = 5
    INVALID_ANSWER = 6
    INTERRUPTED = 130


MEANINGS: dict[ExitCode, str] = {
    ExitCode.OK: "success",
    ExitCode.ERROR: (
        "a local problem: keystore or passphrase, a file that exists or cannot be written, "
        "a size or fee limit, a robot that is not registered"
    ),
    ExitCode.USAGE: "a bad argument, option or setting (such as a ROBOCLOUD_*_URL)",
    ExitCode.UNREACHABLE: ("no answer: connection refused, unknown host or timeout; retry later"),
    ExitCode.REFUSED: (
        "the service said no: a 4xx error, a JSON-RPC error or a contract revert; "
        "the same request will not succeed"
    ),
    ExitCode.UNAVAILABLE: (
        "the service failed or is busy (5xx, 429), has not caught up (409 not_anchored), or "
        "a transaction was not mined in time; retry later"
    ),
    ExitCode.INVALID_ANSWER: (
        "the answer is malformed or failed verification (a CID mismatch, JSON nested too "
        "deep); nothing was written; do not trust that service"
    ),
    ExitCode.INTERRUPTED: "interrupted (Ctrl-C)",
}


def exit_codes_help() -> str:
    """The exit codes as ``--help`` shows them, one per line."""
    return "\n\n".join(f"{int(code)}: {meaning}" for code, meaning in MEANINGS.items())


@dataclass(frozen=True)
class Failure:
    """What the CLI prints and returns for one failure."""

    code: ExitCode
    message: str
    hint: str | None = None


def failure_of(exc: BaseException) -> Failure:
    """The exit code, message and hint for an exception that ended a command."""
    if isinstance(exc, KeyboardInterrupt):
        return Failure(ExitCode.INTERRUPTED, "interrupted")
    if isinstance(exc, OSError):
        return Failure(ExitCode.ERROR, str(exc))
    if isinstance(exc, ConfigurationError):
        return Failure(
            ExitCode.USAGE, str(exc), "check the ROBOCLOUD_*_URL settings and URL options"
        )
    if isinstance(exc, TransportError):
        return _transport(exc)
    if isinstance(exc, ApiError):
        return _api(exc)
    ledger = _ledger_failure(exc)
    if ledger is not None:
        return ledger
    if isinstance(exc, RedirectError):
        return Failure(
            ExitCode.INVALID_ANSWER,
            str(exc),
            "if the service moved, point its ROBOCLOUD_*_URL (or URL option) at where it is now",
        )
    if isinstance(exc, NoSuchPathError):
        return Failure(ExitCode.USAGE, str(exc), "name a path the directory holds")
    if isinstance(exc, NotAFileError):
        return Failure(
            ExitCode.USAGE,
            str(exc),
            "`robocloud get` writes files and directories only",
        )
    if isinstance(exc, LocalContentError):
        return Failure(ExitCode.ERROR, str(exc))
    if isinstance(exc, (InvalidAnswerError, FormatError)):
        return Failure(
            ExitCode.INVALID_ANSWER,
            str(exc),
            "nothing was written; the service is broken or is not a robocloud service",
        )
    return Failure(ExitCode.ERROR, str(exc) or type(exc).__name__)


def _ledger_failure(exc: BaseException) -> Failure | None:
    """The failure for one of the ledger's errors, or None for any other exception.

    A command that never loaded the ledger cannot have raised its errors, and importing them
    here would load the ledger package and its eth-abi (``main.py``) just to print a failed
    ``get``.
    """
    if "robocloud.ledger.errors" not in sys.modules:
        return None
    from robocloud.ledger.errors import (
        FeeLimitError,
        RevertError,
        RpcError,
        TransactionMismatchError,
        TransactionTimeoutError,
    )

    if isinstance(exc, RpcError):
        return Failure(ExitCode.REFUSED, str(exc), _rpc_hint(exc))
    if isinstance(exc, RevertError):
        return Failure(ExitCode.REFUSED, str(exc), _revert_hint(exc))
    if isinstance(exc, TransactionTimeoutError):
        return Failure(
            ExitCode.UNAVAILABLE, str(exc), "it may still be mined; look the hash up later"
        )
    if isinstance(exc, FeeLimitError):
        return Failure(
            ExitCode.ERROR, str(exc), "raise that limit only for a node and a chain you trust"
        )
    if isinstance(exc, TransactionMismatchError):
        return Failure(
            ExitCode.INVALID_ANSWER,
            str(exc),
            f"the transaction was sent and may be mined: look {exc.tx_hash} up on a node you trust",
        )
    return None


def _transport(exc: TransportError) -> Failure:
    if exc.service is None:
        where = "check the URL"
    else:
        setting = f"ROBOCLOUD_{exc.service.upper()}_URL"
        where = f"is the {exc.service} service running? {setting} or --{exc.service} says where"
    if isinstance(exc, TransportTimeoutError):
        return Failure(ExitCode.UNREACHABLE, str(exc), "the service is slow or stuck; retry")
    return Failure(ExitCode.UNREACHABLE, str(exc), where)


_API_HINTS = {
    "address_not_allowed": "run `robocloud register` to register this robot on the ledger",
    "registration_pending": (
        "the ledger's admin or a registrar approves it (`robocloud admin pending` lists who "
        "waits); `robocloud robot` shows its state"
    ),
    "robot_inactive": (
        "`robocloud robot` shows its state; the ledger's admin can reinstate it "
        "(`robocloud admin reinstate`)"
    ),
    "role_required": "the ledger's admin grants roles",
    "stale_timestamp": "check this machine's clock",
    "replayed_nonce": "retry: every attempt is signed with a fresh nonce",
    "faucet_unavailable": "the faucet exists only on the development chain",
    "insufficient_storage": (
        "the service's disk is full, or down to the reserve it keeps: it takes writes again "
        "once data is deleted or its operator frees space"
    ),
    "quota_exceeded": (
        "this robot's share is used up, and waiting does not free it: remove some of its data "
        "(in the cas `robocloud pinned` shows the share, `robocloud unpin CID` frees part)"
    ),
    "not_anchored": (
        "the node anchors a record's epoch seconds after it arrives, unless its anchoring is "
        "stalled (GET /v1/node says why): retry, or `robocloud verify ID --wait 30`"
    ),
}
_OWN_SHARE = frozenset({"quota_exceeded"})
"""5xx codes that only the robot itself can mend: refused, not a service to retry later."""
_NOT_YET = frozenset({"not_anchored"})
"""4xx codes that the same request gets past once the service has caught up: retry later."""


def _api(exc: ApiError) -> Failure:
    request = f" (request id {exc.request_id})" if exc.request_id else ""
    message = f"{exc.status} {exc.code}: {exc.message}{request}"
    hint = _API_HINTS.get(exc.code)
    if isinstance(exc, RateLimitedError):
        after = exc.details.get("retry_after")
        wait = f"in {after} s" if after is not None else "later"
        return Failure(ExitCode.UNAVAILABLE, message, f"try again {wait}")
    if (isinstance(exc, ServerError) and exc.code not in _OWN_SHARE) or exc.code in _NOT_YET:
        return Failure(
            ExitCode.UNAVAILABLE, message, hint or "retry later; the request id finds its log"
        )
    return Failure(ExitCode.REFUSED, message, hint)


def _rpc_hint(exc: RpcError) -> str | None:
    if "insufficient funds" in exc.message.lower():
        return "the robot has no gas: `robocloud register` asks the development faucet"
    return None


def _revert_hint(exc: RevertError) -> str | None:
    if "not an active robot" in exc.reason or "caller is not registered" in exc.reason:
        return "run `robocloud register` first"
    return _REGISTRY_ADMIN_HINTS.get(exc.reason)


_ADMIN_KEYSTORE = (
    "pass the Registry admin's keystore with --keystore (the ledger's "
    "data/ledger/keys/admin.json on the embedded chain)"
)
_REGISTRY_ADMIN_HINTS = {
    "Registry: caller is not the admin": _ADMIN_KEYSTORE,
    "Registry: caller is not a registrar": (
        f"only the admin or an active robot with the registrar role decides: {_ADMIN_KEYSTORE}"
    ),
    "Registry: no pending registration": "`robocloud admin pending` lists who waits",
    "Registry: registration already pending": (
        "the ledger's admin or a registrar must approve it; `robocloud robot` shows its state"
    ),
    "Registry: account is not registered": "`robocloud robot ADDRESS` shows its state",
}


def report(failure: Failure) -> None:
    """Print one line on stderr: ``error: <message> (hint: <hint>)``."""
    line = Text("error: ", style="bold red")
    line.append(untrusted(failure.message, MAX_MESSAGE))
    if failure.hint:
        line.append(f" (hint: {untrusted(failure.hint, MAX_MESSAGE)})")
    console(stderr=True).print(line)
