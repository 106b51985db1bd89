"""The root ``robocloud`` command; each area registers its commands from its own module."""

from __future__ import annotations

import typer

from robocloud.cli import cas, keys, ledger, system

app = typer.Typer(
    name="robocloud",
    help="robocloud: share data, knowledge and computation between robots that need not trust.",
    no_args_is_help=True,
    add_completion=False,
)

for area in (keys, system, cas, ledger):
    area.register(app)
