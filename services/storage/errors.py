"""How the storage service's domain exceptions are answered: status, code and details.

Each engineer's rules sit in their own block of ``ERRORS``, so that additions merge cleanly.
"""

from __future__ import annotations

from robocloud.proofs import RecordIdError
from services.common.errors import ErrorMap, ErrorRule
from services.storage.anchoring import (
    EpochNotFound,
    InvalidConsistencyRange,
    NotAnchored,
    RecordNotFound,
    TemplateNotFound,
)
from services.storage.recordlog import InvalidTemplateId

ERRORS = ErrorMap(
    {
        # ----- record logs, epochs and proofs (engineer anchor) -----
        RecordIdError: ErrorRule(
            400, "invalid_record_id", lambda exc: {"field": "id", "id": exc.text[:200]}
        ),
        InvalidTemplateId: ErrorRule(
            400,
            "invalid_template_id",
            lambda exc: {"field": "id", "template": exc.template_id[:200]},
        ),
        InvalidConsistencyRange: ErrorRule(
            400,
            "invalid_parameter",
            lambda exc: {"field": exc.field, "value": exc.value},
        ),
        RecordNotFound: ErrorRule(404, "record_not_found", lambda exc: {"id": str(exc.record_id)}),
        TemplateNotFound: ErrorRule(
            404, "template_not_found", lambda exc: {"template": exc.template}
        ),
        EpochNotFound: ErrorRule(404, "epoch_not_found", lambda exc: {"epoch": exc.epoch}),
        NotAnchored: ErrorRule(
            409,
            "not_anchored",
            lambda exc: {"id": str(exc.record_id), "epoch": exc.epoch},
        ),
    }
)
