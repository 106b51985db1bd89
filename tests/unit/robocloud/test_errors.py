"""One error tree: whatever the SDK raises, ``except RobocloudError`` catches it."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from types import ModuleType

import pytest

import robocloud
from robocloud.cas import CasError, ContentTooLargeError
from robocloud.errors import (
    ApiError,
    FormatError,
    InvalidAnswerError,
    RobocloudError,
    ServerError,
    TransportError,
    UnavailableError,
    error_class_for,
)
from robocloud.ledger.errors import (
    AddressError,
    ContractsUnavailableError,
    LedgerError,
    RpcError,
)

MODULES = [
    importlib.import_module(info.name)
    for info in pkgutil.walk_packages(robocloud.__path__, "robocloud.")
]
"""Every module of the SDK: a new one with its own exception is checked without a change."""


def exceptions_defined_in(module: ModuleType) -> list[type[BaseException]]:
    return [
        value
        for value in vars(module).values()
        if inspect.isclass(value)
        and issubclass(value, BaseException)
        and value.__module__ == module.__name__
    ]


@pytest.mark.parametrize("module", MODULES, ids=lambda module: module.__name__)
def test_every_exception_the_module_defines_is_a_robocloud_error(module: ModuleType) -> None:
    defined = exceptions_defined_in(module)
    assert [kind for kind in defined if not issubclass(kind, RobocloudError)] == []


def test_the_branches_say_whose_fault_it_is() -> None:
    assert issubclass(CasError, InvalidAnswerError)
    assert issubclass(ContractsUnavailableError, InvalidAnswerError)
    assert issubclass(ContractsUnavailableError, LedgerError)
    assert issubclass(AddressError, FormatError)
    assert issubclass(AddressError, ValueError)
    assert issubclass(ContentTooLargeError, RobocloudError)
    assert not issubclass(TransportError, ApiError)
    assert not issubclass(InvalidAnswerError, ApiError)


def test_an_rpc_error_carries_what_an_api_error_does() -> None:
    error = RpcError("eth_call", -32000, "nope", {"x": 1}, status=200, request_id="r")
    assert (error.code, error.message, error.data, error.request_id) == (
        -32000,
        "nope",
        {"x": 1},
        "r",
    )
    assert error.status == 200
    assert str(error) == "eth_call: nope (JSON-RPC error -32000)"


@pytest.mark.parametrize(
    ("status", "kind"),
    [
        (400, "BadRequestError"),
        (401, "AuthenticationError"),
        (503, "UnavailableError"),
        (502, "ServerError"),
        (418, "ApiError"),
        (599, "ServerError"),
    ],
)
def test_each_status_has_its_class(status: int, kind: str) -> None:
    assert error_class_for(status).__name__ == kind
    assert issubclass(UnavailableError, ServerError)
