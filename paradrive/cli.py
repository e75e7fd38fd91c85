"""The ``paradrive`` command line: the app that gathers the commands of
:mod:`paradrive.commands`, one module each."""

from __future__ import annotations

import importlib
import importlib.util
import logging
import sys

import typer
from rich.markup import escape

from paradrive import __version__
from paradrive.commands.common import console, fail, out
from paradrive.errors import EXIT_USAGE, ConfigError, missing_extra

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Build parallel-trajectory video pairs from single-pass driving logs.")

# Each command: its module (which exposes ``register(app)``) and the library module it drives.
# A command whose library this installation lacks is listed as not available, and says so in one
# line when run. In this order ``paradrive --help`` lists them.
COMMANDS: tuple[tuple[str, str, str], ...] = (
    ("build", "paradrive.commands.build", "paradrive.pipeline.build"),
    ("stages", "paradrive.commands.stages", "paradrive.contracts.specs"),
    ("export", "paradrive.commands.export", "paradrive.ingest.export"),
    ("view", "paradrive.commands.view", "paradrive.view"),
    ("inspect", "paradrive.commands.inspect", "paradrive.inspection"),
    ("eval", "paradrive.commands.eval", "paradrive.evaluation"),
    ("status", "paradrive.commands.status", "paradrive.pipeline.status"),
    ("plan", "paradrive.commands.plan", "paradrive.pipeline.budget"),
    ("train", "paradrive.commands.train", "paradrive.train.runs"),
    ("encode", "paradrive.commands.encode", "paradrive.wan.encode"),
    ("convert", "paradrive.commands.convert", "paradrive.train.convert"),
    ("generate", "paradrive.commands.generate", "paradrive.train.generate"),
)


def version_callback(value: bool) -> None:
    if value:
        out.print(f"paradrive {__version__}")
        raise typer.Exit()


@app.callback()
def main_callback(version: bool = typer.Option(False, "--version", callback=version_callback,
                                               is_eager=True, help="Print the version.")) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


def register_commands(app: typer.Typer, commands: tuple[tuple[str, str, str], ...] = COMMANDS) -> None:
    """Add each command to ``app``; a command whose library is not installed gets a stand-in that
    says so. The library is only looked up here, not imported (``paradrive status`` starts
    without torch)."""
    for command, module_name, library in commands:
        if _installed(library):
            importlib.import_module(module_name).register(app)
        else:
            _register_missing(app, command, library)


def _installed(module_name: str) -> bool:
    try:
        return importlib.util.find_spec(module_name) is not None
    except ModuleNotFoundError:   # a package above it is missing
        return False


def _register_missing(app: typer.Typer, command: str, module_name: str) -> None:
    @app.command(command, context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
                 help=f"(not available in this installation: {module_name} is missing)")
    def _missing() -> None:
        fail(f"'paradrive {command}' is not available: {module_name} is not installed")


register_commands(app)


def main() -> None:
    try:
        app()
    except ConfigError as exc:
        console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
        sys.exit(EXIT_USAGE)
    except ModuleNotFoundError as exc:
        missing = missing_extra(exc)
        if missing is None:
            raise
        console.print(f"[bold red]error:[/] {escape(str(missing))}", soft_wrap=True)
        sys.exit(EXIT_USAGE)


if __name__ == "__main__":
    main()
