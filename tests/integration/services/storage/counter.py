"""Records written the way robots write them: an approved template, then ``POST /v1/records``."""

from __future__ import annotations

from typing import Any

from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.storage import Storage
from tests.procs import ServiceProcess


def counter_record(robot: str, i: int, name: str = "imu") -> dict[str, Any]:
    """Record ``i`` of the counter template ``name@1`` (one int field ``i``)."""
    return {"template": f"{name}@1", "topic": "/t", "robot": robot, "t": i, "data": {"i": i}}


def write_counter_records(
    storage: ServiceProcess, identity: Identity, start: int, stop: int, name: str = "imu"
) -> list[str]:
    """Records ``start`` to ``stop`` of ``name@1`` in one batch, its template approved first."""
    template_id = f"{name}@1"
    with Storage(storage.url, identity, retries=0) as client:
        try:
            client.template(template_id)
        except ApiError as exc:
            if exc.status != 404:
                raise
            client.create_template({"name": name, "version": 1, "fields": {"i": "int"}})
            client.submit_template(template_id)
            client.review_template(template_id, "approve", "test template")
        records = [counter_record(identity.address, i, name) for i in range(start, stop)]
        return client.append(records)
