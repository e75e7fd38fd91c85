"""The command line gathers its commands from paradrive/commands, one module each, in the order
``paradrive --help`` lists them; a command whose library this installation lacks is listed as
not available and says so in one line (exit 2) instead of breaking the others."""

from __future__ import annotations

import re

import typer
from typer.testing import CliRunner

from paradrive import cli


def _listed(app: typer.Typer) -> list[str]:
    """The commands ``--help`` lists, in its order."""
    shown = CliRunner().invoke(app, ["--help"], env={"COLUMNS": "200"}).output
    return re.findall(r"^│ (\w+) ", shown, re.M)


def test_help_lists_every_command_module_in_order():
    assert _listed(cli.app) == [command for command, _, _ in cli.COMMANDS]
    assert [module for _, module, _ in cli.COMMANDS] == [
        f"paradrive.commands.{command}" for command, _, _ in cli.COMMANDS]


def test_a_command_whose_library_is_missing_says_so_and_the_others_run():
    app = typer.Typer()
    cli.register_commands(app, (
        ("stages", "paradrive.commands.stages", "paradrive.contracts.specs"),
        ("ghost", "paradrive.commands.status", "paradrive.no_such_module"),
        ("phantom", "paradrive.commands.status", "paradrive_no_such_package.module"),
    ))
    shown = CliRunner().invoke(app, ["--help"], env={"COLUMNS": "200"}).output
    assert "(not available in this installation: paradrive.no_such_module is missing)" in shown
    assert "(not available in this installation: paradrive_no_such_package.module is missing)" in shown
    ran = CliRunner().invoke(app, ["ghost", "build-a", "--json"])
    assert ran.exit_code == 2
    assert ran.output == "error: 'paradrive ghost' is not available: paradrive.no_such_module is not installed\n"
    assert CliRunner().invoke(app, ["stages", "ingest"]).exit_code == 0
