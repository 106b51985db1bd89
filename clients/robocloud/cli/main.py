"""The root ``robocloud`` command; each area registers its commands from its own module.

``RobocloudGroup.invoke`` is the one place a command's failure becomes a one-line message and
an exit code (``exits.py``): every SDK error is a ``RobocloudError``, local files raise
``OSError``, and neither prints a traceback. It is also where the recursion limit is put
back: py_ecc (imported by eth-account) raises it to 100,000 at import, and with that limit
deep recursion in C code (a JSON decoder fed hostile nesting) overflows the C stack and
kills the process instead of raising ``RecursionError``.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any

import typer
from typer.core import TyperGroup

import robocloud
from robocloud.cli import admin, cas, ingest, keys, knowledge, ledger, storage, system, verify
from robocloud.cli.exits import ExitCode, exit_codes_help, failure_of, report
from robocloud.errors import RobocloudError

RECURSION_LIMIT = 1000
"""CPython's own default: deep enough for any command, shallow enough for the C stack."""


class RobocloudGroup(TyperGroup):
    """The root group: runs a command under a sane recursion limit and reports its failure."""

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
    rich_markup_mode="markdown",
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


for area in (keys, system, cas, ledger, admin, storage, ingest, verify, knowledge):
    area.register(app)
