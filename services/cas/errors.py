"""How the cas's domain exceptions are answered: status, code and details, in one place."""

from __future__ import annotations

from robocloud.directory import NotADirectory, PathNotFound
from services.cas.multipart import MultipartError, NotMultipart, TruncatedMultipart
from services.cas.pins import NotPinned, PinNotOwned, PinQuotaExceeded
from services.cas.ranges import InvalidEntityBytes, UnsatisfiableRange
from services.cas.shares import WriteRateExceeded
from services.cas.store import (
    BlockUnavailable,
    CarRejected,
    DagIncomplete,
    InvalidDag,
    NotAFile,
    ReadBudgetExceeded,
    TooManyEntries,
    UnknownScope,
    UnpinnedArgument,
)
from services.cas.uploads import (
    DirectoryPart,
    InvalidBlock,
    InvalidPath,
    NoFilePart,
    TooManyParts,
    TooManyRoots,
)
from services.common.errors import ErrorMap, ErrorRule


def _cid(
    exc: BlockUnavailable | NotAFile | InvalidDag | NotPinned | UnpinnedArgument,
) -> dict[str, str]:
    return {"cid": str(exc.cid)}


def _budget(exc: ReadBudgetExceeded) -> dict[str, str | int]:
    """The block the reads stopped at and the limit, with the parameter that asked for
    them when there is one (``arg``; a gateway path is no parameter)."""
    details: dict[str, str | int] = {} if exc.field is None else {"field": exc.field}
    return details | {"cid": str(exc.cid), "limit_bytes": exc.limit}


ERRORS = ErrorMap(
    {
        BlockUnavailable: ErrorRule(404, "block_not_found", _cid),
        DagIncomplete: ErrorRule(
            404,
            "block_not_found",
            lambda exc: {"cid": str(exc.root), "missing": str(exc.missing)},
        ),
        NotAFile: ErrorRule(400, "not_a_file", _cid),
        InvalidDag: ErrorRule(400, "invalid_dag", _cid),
        CarRejected: ErrorRule(400, "invalid_car"),
        ReadBudgetExceeded: ErrorRule(400, "too_much_to_read", _budget),
        TooManyEntries: ErrorRule(
            400,
            "too_many_entries",
            lambda exc: {"cid": str(exc.directory), "limit": exc.limit},
        ),
        UnknownScope: ErrorRule(400, "invalid_dag_scope", lambda _: {"field": "dag-scope"}),
        UnpinnedArgument: ErrorRule(400, "not_pinned", _cid),
        NotPinned: ErrorRule(404, "not_pinned", _cid),
        PinQuotaExceeded: ErrorRule(
            507,
            "quota_exceeded",
            lambda exc: {
                "robot": exc.owner,
                "size": exc.size,
                "used": exc.used,
                "limit": exc.limit,
            },
        ),
        WriteRateExceeded: ErrorRule(
            429,
            "write_rate_exceeded",
            lambda exc: {
                "robot": exc.robot,
                "size": exc.size,
                "written": exc.written,
                "limit": exc.limit,
                "retry_after": exc.retry_after_s,
            },
            headers=lambda exc: {"Retry-After": str(exc.retry_after_s)},
        ),
        PinNotOwned: ErrorRule(
            403, "pin_not_owned", lambda exc: {"cid": str(exc.cid), "address": exc.owner}
        ),
        NotMultipart: ErrorRule(
            415,
            "unsupported_media_type",
            lambda exc: {"header": "Content-Type", "received": exc.content_type},
        ),
        MultipartError: ErrorRule(
            400,
            "invalid_multipart",
            lambda exc: {"header": exc.header} if exc.header else {},
        ),
        TruncatedMultipart: ErrorRule(400, "truncated_multipart"),
        DirectoryPart: ErrorRule(400, "unsupported_part", lambda exc: {"part": exc.name}),
        NoFilePart: ErrorRule(400, "no_file"),
        InvalidPath: ErrorRule(400, "invalid_path", lambda exc: {"part": exc.name}),
        TooManyParts: ErrorRule(
            413, "too_many_entries", lambda exc: {"field": "entries", "limit": exc.limit}
        ),
        InvalidBlock: ErrorRule(400, "invalid_block", lambda exc: {"index": exc.index}),
        TooManyRoots: ErrorRule(
            400,
            "too_many_roots",
            lambda exc: {"field": "roots", "count": exc.count, "limit": exc.limit},
        ),
        PathNotFound: ErrorRule(
            404, "path_not_found", lambda exc: {"segment": exc.segment, "cid": str(exc.at)}
        ),
        NotADirectory: ErrorRule(
            400, "not_a_directory", lambda exc: {"segment": exc.segment, "cid": str(exc.at)}
        ),
        InvalidEntityBytes: ErrorRule(
            400, "invalid_entity_bytes", lambda _: {"field": "entity-bytes"}
        ),
        UnsatisfiableRange: ErrorRule(
            416,
            "range_not_satisfiable",
            lambda exc: {"header": "Range", "size": exc.size},
            lambda exc: {"Content-Range": f"bytes */{exc.size}"},
        ),
    }
)
