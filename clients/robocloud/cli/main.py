"""The root ``robocloud`` command; each area registers its commands from its own module.

The root loads a command's module only when that command runs (``COMMAND_AREAS``): each
area imports what it needs, and the ledger's eth-abi, the knowledge base's rdflib and
eth-utils together took about 0.3 s, which ``robocloud get`` paid on every run although it
needs none of them. ``--help`` lists every command and so loads every area.

``RobocloudGroup.invoke`` is the one place a command's failure becomes a one-line message and
an exit code (``exits.py``): every SDK error is a ``RobocloudError``, local files raise
``OSError``, and neither prints a traceback. It is also where the recursion limit is put
back: py_ecc (imported by eth-account) raises it to 100,000 at import, and with that limit
deep recursion in C code (a JSON decoder fed hostile nesting) overflows the C stack and
kills the process instead of raising ``RecursionError``.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
from typing import Any, Final

import typer
from typer.core import TyperGroup
from typer.main import get_group

import robocloud
from robocloud.cli.exits import ExitCode, exit_codes_help, failure_of, report
from robocloud.errors import RobocloudError

RECURSION_LIMIT = 1000
"""CPython's own default: deep enough for any command, shallow enough for the C stack."""

MARKUP_MODE: Final = "markdown"
"""Help text is Markdown: a paragraph's lines wrap as one, ``code`` shows as code."""

COMMAND_AREAS: dict[str, str] = {
    "status": "system",
    "whoami": "system",
    "put": "cas",
    "get": "cas",
    "cat": "cas",
    "pin": "cas",
    "unpin": "cas",
    "pins": "cas",
    "pinned": "cas",
    "register": "ledger",
    "advertise": "ledger",
    "robot": "ledger",
    "query": "storage",
    "export": "storage",
    "intervals": "storage",
    "ingest": "ingest",
    "job": "ingest",
    "bind": "ingest",
    "verify": "verify",
    "describe": "knowledge",
    "sparql": "knowledge",
    "keys": "keys",
    "admin": "admin",
    "templates": "storage",
}
"""Each top-level command and the ``robocloud.cli`` module whose ``register`` adds it, in the
order ``--help`` lists them."""


class RobocloudGroup(TyperGroup):
    """The root group: loads a command's area on first use, runs the command under a sane
    recursion limit and reports its failure."""

    def list_commands(self, ctx: Any) -> list[str]:
        return list(COMMAND_AREAS)

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        """The command, its area loaded first; for a name of none, every area is loaded,
        so that typer's "Did you mean" has every command to choose from."""
        if cmd_name not in self.commands:
            area = COMMAND_AREAS.get(cmd_name)
            for each in set(COMMAND_AREAS.values()) if area is None else {area}:
                self.commands.update(area_commands(each))
        return self.commands.get(cmd_name)

    def invoke(self, ctx: Any) -> Any:  # typer vendors click; its Context type is private
        previous = sys.getrecursionlimit()
        sys.setrecursionlimit(RECURSION_LIMIT)
        try:
            return super().invoke(ctx)
        except BrokenPipeError:
            _silence_stdout()
            raise typer.Exit(int(ExitCode.ERROR)) from None
        except (RobocloudError, OSError, KeyboardInterrupt) as exc:
            failure = failure_of(exc)
            report(failure)
            raise typer.Exit(int(failure.code)) from None
        finally:
            sys.setrecursionlimit(previous)


def area_commands(area: str) -> dict[str, Any]:
    """The click commands that the module ``robocloud.cli.<area>`` registers, by name,
    rendering their help as the root does (a command takes its app's markup mode)."""
    module = importlib.import_module(f"robocloud.cli.{area}")
    commands = typer.Typer(rich_markup_mode=MARKUP_MODE)
    module.register(commands)
    return dict(get_group(commands).commands)


def _silence_stdout() -> None:
    """The reader of stdout went away (``robocloud pins | head -1``): say nothing more.

    Pointing stdout at /dev/null keeps the interpreter's final flush from failing again.
    """
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())


app = typer.Typer(
    name="robocloud",
    cls=RobocloudGroup,
    help="robocloud: share data, knowledge and computation between robots that need not trust.",
    epilog=f"Exit codes (docs/cli.md):\n\n{exit_codes_help()}",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=MARKUP_MODE,
    pretty_exceptions_show_locals=False,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"robocloud {robocloud.__version__}")
        raise typer.Exit(int(ExitCode.OK))


@app.callback()
def root(
    version: bool = typer.Option(
        False,
        "--version",
        help="Print the version and exit.",
        callback=_print_version,
        is_eager=True,
    ),
) -> None:
    """robocloud: share data, knowledge and computation between robots that need not trust."""
