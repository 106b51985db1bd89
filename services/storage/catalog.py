"""The template catalog: versions of each template and their review lifecycle.

A version is born a ``draft`` (edited freely by its author), is ``submitted`` for review, and
a robot holding the ``reviewer`` role ``approved`` or ``rejected`` it. Records are accepted
only against approved versions, and an approved version never changes: records and their
Merkle leaves refer to it by id, so an edit would silently retype data already proven. An
edit of an approved version is refused; the designer makes a new version instead. A rejected
version may be edited, which makes it a draft again.

The catalog lives in memory, bounded in versions and in bytes (a version's fields may hold
a hundred kilobytes, so a count alone let 100,000 of them take 79 GiB); every change is one
fsynced line of a journal, compacted at each start, so a change acknowledged survives kill -9.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

from robocloud.jcs import canonical
from robocloud.templates import (
    MAX_VERSION,
    Problem,
    Template,
    TemplateInvalid,
    evaluate,
    parse_template,
    parse_template_id,
)
from services.common.durable import AppendLog

Status = Literal["draft", "submitted", "approved", "rejected"]
STATUSES: tuple[Status, ...] = ("draft", "submitted", "approved", "rejected")
Decision = Literal["approve", "reject"]
MAX_REASON = 1024
DEFAULT_MAX_VERSIONS = 100_000
DEFAULT_MAX_BYTES = 64 * 1024 * 1024
"""Bytes of the versions' journal lines, which their size in memory follows (about 5x)."""


class CatalogError(Exception):
    """Base of the catalog's own errors."""


class TemplateNotFound(CatalogError, LookupError):
    def __init__(self, template_id: str) -> None:
        super().__init__(f"no template {template_id}")
        self.template_id = template_id


class TemplateExists(CatalogError):
    def __init__(self, name: str) -> None:
        super().__init__(
            f"template {name} exists; POST /v1/templates/{name}/versions makes a new version"
        )
        self.name = name


class TemplateImmutable(CatalogError):
    """An edit of a version that is under review or approved."""

    def __init__(self, template_id: str, status: Status) -> None:
        hint = "make a new version instead" if status == "approved" else "it is under review"
        super().__init__(f"template {template_id} is {status} and cannot be edited; {hint}")
        self.template_id = template_id
        self.status = status


class LifecycleConflict(CatalogError):
    """A step the version's current status does not allow (approving a draft)."""

    def __init__(self, template_id: str, status: Status, action: str) -> None:
        super().__init__(f"template {template_id} is {status}; it cannot be {action}")
        self.template_id = template_id
        self.status = status
        self.action = action


class NotAuthor(CatalogError):
    def __init__(self, template_id: str, address: str, author: str) -> None:
        super().__init__(f"template {template_id} belongs to {author}, not {address}")
        self.template_id = template_id
        self.address = address
        self.author = author


class TemplateNotApproved(CatalogError):
    """Records were sent for a version that is not approved."""

    def __init__(self, template_id: str, status: Status) -> None:
        super().__init__(f"template {template_id} is {status}; records need an approved version")
        self.template_id = template_id
        self.status = status


class CatalogFull(CatalogError):
    def __init__(self, limit: int, unit: str = "template versions") -> None:
        super().__init__(f"the catalog holds its limit of {limit} {unit}")
        self.limit = limit
        self.unit = unit


@dataclass(frozen=True)
class TemplateVersion:
    """One version of a template with where it stands in review."""

    template: Template
    status: Status
    author: str
    created_at: int
    updated_at: int
    reviewer: str | None = None
    reason: str | None = None

    @property
    def id(self) -> str:
        return self.template.id

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            **self.template.to_json(),
            "status": self.status,
            "author": self.author,
            "created_at": self.created_at,
            "updated_at": self.updated_at,
            "reviewer": self.reviewer,
            "reason": self.reason,
        }

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> TemplateVersion:
        template = parse_template(
            {key: document[key] for key in ("name", "version", "fields", "description")}
        )
        status = document["status"]
        if status not in STATUSES:
            raise ValueError(f"unknown status {status!r}")
        return cls(
            template,
            status,
            str(document["author"]),
            int(document["created_at"]),
            int(document["updated_at"]),
            document.get("reviewer"),
            document.get("reason"),
        )


def _line(version: TemplateVersion) -> str:
    return json.dumps(version.to_json(), separators=(",", ":"))


def _evaluated(document: Any, name: str, version: int) -> Template:
    """``document`` (fields, description; name and version optional) as version ``version``."""
    if not isinstance(document, dict):
        raise TemplateInvalid([Problem("", "a template is an object")])
    problems = []
    if document.get("name", name) != name:
        problems.append(Problem("name", f"must be {name} here"))
    given = document.get("version", version)
    # true == 1 and 1.0 == 1 in Python: a version that is not an integer is not this one.
    if isinstance(given, bool) or not isinstance(given, int) or given != version:
        problems.append(Problem("version", f"must be the integer {version} (the next version)"))
    template, found = evaluate({**document, "name": name, "version": version})
    problems.extend(found)
    if template is None or problems:
        raise TemplateInvalid(problems)
    return template


def fields_key(template: Template) -> bytes:
    """A digest of ``template``'s fields alone (not its name, version or description)."""
    fields = canonical(template.to_json()["fields"])
    return hashlib.sha256(fields).digest()


def _index_approved(by_fields: dict[bytes, set[str]], version: TemplateVersion) -> None:
    if version.status == "approved":
        by_fields.setdefault(fields_key(version.template), set()).add(version.id)


class Catalog:
    """Template versions by id, persisted in ``root/catalog.log``."""

    def __init__(
        self,
        root: Path,
        *,
        max_versions: int = DEFAULT_MAX_VERSIONS,
        max_bytes: int = DEFAULT_MAX_BYTES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.max_versions = max_versions
        self.max_bytes = max_bytes
        self.clock = clock
        self._lock = threading.Lock()
        self._versions: dict[str, TemplateVersion] = {}
        self._sizes: dict[str, int] = {}
        """Each version's journal line, in bytes; their sum is what ``max_bytes`` bounds."""
        self._bytes = 0
        self._latest: dict[str, int] = {}
        self._approved_by_fields: dict[bytes, set[str]] | None = None
        """Approved versions by :func:`fields_key`, for an unbound topic's draft to find
        one it fits among up to ``max_versions``; built at the first such search (17 µs a
        version, which a start need not spend), then kept up to date."""
        self._journal = AppendLog(root / "catalog.log")
        lines = self._journal.read_lines()
        for line in lines:
            self._remember(TemplateVersion.from_json(json.loads(line)), len(line))
        self._journal.compact_at_open([_line(v) for v in self._versions.values()], len(lines))

    def close(self) -> None:
        self._journal.close()

    def _remember(self, version: TemplateVersion, size: int) -> None:
        self._bytes += size - self._sizes.get(version.id, 0)
        self._sizes[version.id] = size
        earlier = self._versions.get(version.id)
        self._versions[version.id] = version
        by_fields = self._approved_by_fields
        if by_fields is not None:
            if earlier is not None and earlier.status == "approved":
                by_fields[fields_key(earlier.template)].discard(version.id)
            _index_approved(by_fields, version)
        name = version.template.name
        self._latest[name] = max(self._latest.get(name, 0), version.template.version)

    def _store(self, version: TemplateVersion) -> TemplateVersion:
        """Journal and keep ``version``; :class:`CatalogFull` when it would take the catalog
        past ``max_bytes`` (an edit counts as the change in its size)."""
        line = _line(version)
        if self._bytes - self._sizes.get(version.id, 0) + len(line) > self.max_bytes:
            raise CatalogFull(self.max_bytes, "bytes of templates")
        self._journal.append(line)
        self._remember(version, len(line))
        return version

    def _now(self) -> int:
        return int(self.clock())

    def _get(self, template_id: str) -> TemplateVersion:
        version = self._versions.get(template_id)
        if version is None:
            raise TemplateNotFound(template_id)
        return version

    def _new(self, template: Template, author: str) -> TemplateVersion:
        if len(self._versions) >= self.max_versions:
            raise CatalogFull(self.max_versions)
        now = self._now()
        return self._store(TemplateVersion(template, "draft", author, now, now))

    def create(self, document: Any, *, author: str) -> TemplateVersion:
        """A new template's first version, a draft; :class:`TemplateExists` if the name is taken."""
        name = document.get("name") if isinstance(document, dict) else None
        if not isinstance(name, str):
            raise TemplateInvalid(evaluate(document)[1])
        template = _evaluated(document, name, 1)
        with self._lock:
            if name in self._latest:
                raise TemplateExists(name)
            return self._new(template, author)

    def new_version(self, name: str, document: Any, *, author: str) -> TemplateVersion:
        """The next version of ``name`` (a draft) from ``document``'s fields and description."""
        with self._lock:
            latest = self._latest.get(name)
            if latest is None:
                raise TemplateNotFound(name)
            if latest >= MAX_VERSION:
                raise CatalogFull(self.max_versions)
            template = _evaluated(document, name, latest + 1)
            return self._new(template, author)

    def edit(self, template_id: str, document: Any, *, author: str) -> TemplateVersion:
        """Replace a draft's (or a rejected version's) fields; it is a draft afterwards."""
        name, number = parse_template_id(template_id)
        with self._lock:
            current = self._get(template_id)
            if current.status in ("approved", "submitted"):
                raise TemplateImmutable(template_id, current.status)
            if current.author != author:
                raise NotAuthor(template_id, author, current.author)
            template = _evaluated(document, name, number)
            edited = replace(
                current,
                template=template,
                status="draft",
                updated_at=self._now(),
                reviewer=None,
                reason=None,
            )
            return self._store(edited)

    def submit(self, template_id: str, *, author: str) -> TemplateVersion:
        """A draft goes to review; only its author submits it."""
        with self._lock:
            current = self._get(template_id)
            if current.status != "draft":
                raise LifecycleConflict(template_id, current.status, "submitted")
            if current.author != author:
                raise NotAuthor(template_id, author, current.author)
            return self._store(replace(current, status="submitted", updated_at=self._now()))

    def review(
        self, template_id: str, decision: Decision, *, reviewer: str, reason: str | None = None
    ) -> TemplateVersion:
        """Approve or reject a submitted version (the caller checked the reviewer role)."""
        with self._lock:
            current = self._get(template_id)
            action = "approved" if decision == "approve" else "rejected"
            if current.status != "submitted":
                raise LifecycleConflict(template_id, current.status, action)
            reviewed = replace(
                current,
                status="approved" if decision == "approve" else "rejected",
                updated_at=self._now(),
                reviewer=reviewer,
                reason=reason,
            )
            return self._store(reviewed)

    def get(self, template_id: str) -> TemplateVersion:
        parse_template_id(template_id)
        with self._lock:
            return self._get(template_id)

    def approved(self, template_id: str) -> Template:
        """The approved template of ``template_id``, for records to be validated against."""
        version = self.get(template_id)
        if version.status != "approved":
            raise TemplateNotApproved(template_id, version.status)
        return version.template

    def approved_like(self, template: Template) -> list[str]:
        """Approved versions with ``template``'s fields, oldest first: an unbound topic
        whose draft has them is bound to one rather than a template made again (its name
        taken, the draft's ``templates create`` is a 409)."""
        with self._lock:
            if self._approved_by_fields is None:
                self._approved_by_fields = {}
                for version in self._versions.values():
                    _index_approved(self._approved_by_fields, version)
            fitting = list(self._approved_by_fields.get(fields_key(template), ()))
        return sorted(fitting, key=parse_template_id)

    def list(
        self,
        *,
        name: str | None = None,
        status: Status | None = None,
        after: str | None = None,
        limit: int = 100,
    ) -> list[TemplateVersion]:
        """Versions ordered by name then version, those after the id ``after`` (a cursor)."""
        start = parse_template_id(after) if after is not None else None
        with self._lock:
            versions = list(self._versions.values())
        chosen = sorted(
            (
                v
                for v in versions
                if (name is None or v.template.name == name)
                and (status is None or v.status == status)
            ),
            key=lambda v: (v.template.name, v.template.version),
        )
        if start is not None:
            chosen = [v for v in chosen if (v.template.name, v.template.version) > start]
        return chosen[:limit]

    def page(
        self,
        *,
        name: str | None = None,
        status: Status | None = None,
        after: str | None = None,
        limit: int = 100,
        max_bytes: int,
    ) -> tuple[tuple[TemplateVersion, ...], bool]:
        """At most ``limit`` versions in ``list``'s order and at most ``max_bytes`` of them
        (always one), and whether more follow: a thousand large versions made one answer of
        tens of megabytes."""
        versions = self.list(name=name, status=status, after=after, limit=limit + 1)
        taken = 0
        size = 0
        for version in versions[:limit]:
            size += self._sizes.get(version.id, 0)
            if taken and size > max_bytes:
                break
            taken += 1
        return tuple(versions[:taken]), taken < len(versions)
