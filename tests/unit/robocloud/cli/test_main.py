"""The root command: version, help that documents itself, and one way of failing."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import typer
from typer.main import get_command
from typer.testing import CliRunner

import robocloud
from robocloud.cli import app
from robocloud.cli.exits import MEANINGS
from robocloud.cli.main import COMMAND_AREAS, RECURSION_LIMIT, RobocloudGroup, area_commands
from robocloud.errors import InvalidAnswerError
from tests.fresh_interpreter import printed_by

runner = CliRunner()
DOCS = Path(__file__).resolve().parents[4] / "docs" / "cli.md"


def leaf_commands() -> dict[str, typer.core.TyperCommand]:
    """Every command a user can run, by its full name (``keys new``)."""
    found = {}
    pending = [("", get_command(app))]
    context = typer.Context(get_command(app))
    while pending:
        prefix, group = pending.pop()
        for name in group.list_commands(context):  # type: ignore[attr-defined]
            command = group.get_command(context, name)  # type: ignore[attr-defined]
            if hasattr(command, "commands"):
                pending.append((f"{prefix}{name} ", command))
            else:
                found[f"{prefix}{name}"] = command
    return found


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.stdout == f"robocloud {robocloud.__version__}\n"


def test_help_lists_every_exit_code() -> None:
    result = runner.invoke(app, ["--help"], env={"COLUMNS": "300"})
    assert result.exit_code == 0
    text = " ".join(result.stdout.split())
    for code, meaning in MEANINGS.items():
        assert f"{int(code)}: {meaning}" in text


def test_the_docs_list_the_same_exit_codes() -> None:
    documented = dict(re.findall(r"^\| `(\d+)` \| (.+?) \|$", DOCS.read_text(), re.MULTILINE))
    assert documented == {str(int(code)): meaning for code, meaning in MEANINGS.items()}


def test_every_command_prints_json_on_request_and_documents_its_parameters() -> None:
    commands = leaf_commands()
    assert {"put", "get", "pins", "robot", "status", "keys new", "keys show"} <= set(commands)
    for name, command in commands.items():
        options = {opt for param in command.params for opt in param.opts}
        assert "--json" in options, name
        for param in command.params:
            assert getattr(param, "help", None), f"{name} {param.name} has no help"


def test_help_shows_argument_names_and_defaults() -> None:
    result = runner.invoke(app, ["get", "--help"], env={"COLUMNS": "300"})
    text = " ".join(result.stdout.split())
    assert "Usage: robocloud get [OPTIONS] {CID[/PATH]}" in text
    assert "[default: (the free space in OUTPUT's directory)]" in text
    assert "[default: ($ROBOCLOUD_CAS_URL, else http://127.0.0.1:8080)]" in text


def test_commands_run_under_a_sane_recursion_limit_which_is_then_restored() -> None:
    """py_ecc, once imported, raises the limit; a command runs under CPython's own."""
    original = sys.getrecursionlimit()
    sys.setrecursionlimit(100_000)
    try:
        run_a_command_under_a_raised_recursion_limit()
    finally:
        sys.setrecursionlimit(original)


def run_a_command_under_a_raised_recursion_limit() -> None:
    seen: list[int] = []
    probe = typer.Typer(cls=RobocloudGroup)

    @probe.command()
    def depth() -> None:
        seen.append(sys.getrecursionlimit())

    @probe.command()
    def other() -> None:
        """Two commands, so that ``depth`` is a subcommand like the real ones."""

    before = sys.getrecursionlimit()
    assert before > RECURSION_LIMIT
    assert runner.invoke(probe, ["depth"]).exit_code == 0
    assert seen == [RECURSION_LIMIT]
    assert sys.getrecursionlimit() == before


def test_a_robocloud_error_is_one_line_on_stderr_with_its_exit_code() -> None:
    probe = typer.Typer(cls=RobocloudGroup)

    @probe.command()
    def lie() -> None:
        raise InvalidAnswerError("the cas service sent\n\x1b[31mforged lines")

    @probe.command()
    def other() -> None:
        """Two commands, so that ``lie`` is a subcommand like the real ones."""

    result = runner.invoke(probe, ["lie"])
    assert result.exit_code == 6
    assert result.stdout == ""
    assert result.stderr.count("\n") == 1
    assert result.stderr.startswith("error: the cas service sent\\n\\x1b[31mforged lines (hint: ")
    assert "Traceback" not in result.stderr


def test_an_os_error_is_one_line_without_traceback(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "dir" / "out.bin"
    cid = "bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq"
    result = runner.invoke(app, ["get", cid, "-o", str(missing), "--cas", "http://127.0.0.1:9"])
    assert result.exit_code == 1
    assert result.stdout == ""
    assert result.stderr.startswith("error: [Errno 2] No such file or directory")
    assert result.stderr.count("\n") == 1


def test_each_command_is_loaded_from_the_area_that_registers_it() -> None:
    for area in set(COMMAND_AREAS.values()):
        named = [name for name, its_area in COMMAND_AREAS.items() if its_area == area]
        assert sorted(area_commands(area)) == sorted(named), area


def test_help_lists_the_commands_in_the_order_of_the_map() -> None:
    result = runner.invoke(app, ["--help"], env={"COLUMNS": "300"})
    listed = re.findall(r"^│ (\w+) ", result.stdout, re.MULTILINE)
    assert listed == list(COMMAND_AREAS)


def test_every_command_renders_its_help_as_markdown() -> None:
    """Loaded apart from the root, the commands had lost its markup mode: a paragraph of
    help kept its source's line breaks, ragged at 80 columns, and ``--drafts`` showed its
    backquotes."""
    assert {command.rich_markup_mode for command in leaf_commands().values()} == {"markdown"}
    shown = runner.invoke(app, ["get", "--help"], env={"COLUMNS": "80"}).stdout
    assert "leaves nothing behind. A directory's entries are checked" in shown


def test_a_mistyped_command_is_answered_with_the_ones_near_it() -> None:
    result = runner.invoke(app, ["gett", "x"], env={"COLUMNS": "300"})
    assert result.exit_code == 2
    assert "No such command 'gett'. Did you mean 'get', 'ingest'?" in result.stderr


def test_a_content_command_loads_neither_the_ledger_nor_the_knowledge_libraries(
    tmp_path: Path,
) -> None:
    """eth-abi (the ledger package), rdflib (the knowledge base) and eth-utils took about
    0.3 s of every command's start; ``get`` needs none of them, even to report a failure.
    A command of the knowledge base then loads what it needs."""
    probe = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from robocloud.cli import app\n"
        "cid = 'bafkreide5semuafsnds3ugrvm6fbwuyw2ijpj43gwjdxemstjkfozi37hq'\n"
        f"out = {str(tmp_path / 'out')!r}\n"
        "got = CliRunner().invoke(app, ['get', cid, '-o', out, '--cas', 'http://127.0.0.1:9'])\n"
        "heavy = ('eth_abi', 'eth_utils', 'rdflib', 'eth_account')\n"
        "print(got.exit_code, [name for name in heavy if name in sys.modules])\n"
        "assert CliRunner().invoke(app, ['sparql', '--help']).exit_code == 0\n"
        "print([name for name in heavy if name in sys.modules])\n"
    )
    assert printed_by(probe).splitlines() == ["3 []", "['eth_abi', 'eth_utils', 'rdflib']"]


def test_a_command_that_signs_nothing_loads_no_signing_library() -> None:
    """eth-account takes about a second to import (eth-keyfile loads py_ecc's BLS pairing
    tables); ``get``, ``cat``, ``verify`` and ``--help`` never sign, so they must not pay it.
    A key created then loads it."""
    probe = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from robocloud.cli import app\n"
        "assert CliRunner().invoke(app, ['verify', '--help']).exit_code == 0\n"
        "print('eth_account' in sys.modules)\n"
        "from robocloud.identity import Identity\n"
        "Identity.generate()\n"
        "print('eth_account' in sys.modules)\n"
    )
    assert printed_by(probe).split() == ["False", "True"]
