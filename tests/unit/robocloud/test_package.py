"""``import robocloud`` is cheap: services read ``__version__`` and scripts catch its errors.

Checked in a fresh interpreter, since this test process has long imported everything.
"""

from __future__ import annotations

import json

import pytest

import robocloud
from tests.fresh_interpreter import printed_by

HEAVY = ("httpx", "eth_account", "eth_utils", "py_ecc", "rich", "typer")


def modules_loaded_by(statement: str) -> list[str]:
    code = f"import sys\n{statement}\nprint(__import__('json').dumps(sorted(sys.modules)))"
    loaded: list[str] = json.loads(printed_by(code).splitlines()[-1])
    return loaded


@pytest.mark.parametrize(
    "statement",
    [
        "import robocloud; robocloud.__version__",
        "from robocloud.errors import RobocloudError, TransportError, ApiError",
        "import robocloud.config",
    ],
)
def test_the_package_and_its_errors_import_nothing_heavy(statement: str) -> None:
    loaded = modules_loaded_by(statement)
    assert [name for name in HEAVY if name in loaded] == []


def test_the_re_exports_load_on_first_use() -> None:
    loaded = modules_loaded_by("import robocloud; robocloud.ServiceClient")
    assert "httpx" in loaded
    from robocloud.client import ServiceClient
    from robocloud.errors import TransportError

    assert robocloud.ServiceClient is ServiceClient
    assert robocloud.TransportError is TransportError
    assert set(robocloud.__all__) <= set(dir(robocloud))


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        robocloud.Nope  # noqa: B018
