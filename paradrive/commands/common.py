"""What the commands share: the two consoles, the one-line error, the defaults of the options
several commands take."""

from __future__ import annotations

from pathlib import Path
from typing import NoReturn

import typer
from rich.console import Console
from rich.markup import escape

from paradrive.errors import EXIT_USAGE

# Output to a pipe or a file is read by scripts (grep, cut): lines that long never wrap, so a
# table is printed at its natural width and no name or value in it is cut.
PIPE_WIDTH = 10_000


def new_console(stderr: bool = False) -> Console:
    """A console for stdout (or stderr): on a terminal, the terminal's width (COLUMNS when set);
    on a pipe or a file, :data:`PIPE_WIDTH`."""
    made = Console(stderr=stderr)
    return made if made.is_terminal else Console(stderr=stderr, width=PIPE_WIDTH)


# Made at import: the build's progress and result lines, errors and notes, and what build,
# stages, export and view report. A command whose tables follow the terminal's width when it
# runs (inspect, status, eval, plan) makes its own consoles then: a Console takes COLUMNS when
# it is made.
console = new_console(stderr=True)
out = new_console()

DEFAULT_DATA = Path("data")
DEFAULT_MANIFESTS = Path("manifests")
DEFAULT_SCENE = "synthetic:demo?seed=7"


def error_line(message: str) -> str:
    """The markup of an error line; ``message`` is printed verbatim."""
    return f"[bold red]error:[/] {escape(message)}"


def fail(message: str, code: int = EXIT_USAGE, *, err: Console | None = None,
         soft_wrap: bool = True) -> NoReturn:
    """Print ``error: message`` on stderr (``err``, default :data:`console`; one line whatever
    the width, unless ``soft_wrap`` is False) and end the command with exit code ``code``."""
    (err or console).print(error_line(message), soft_wrap=soft_wrap)
    raise typer.Exit(code)


def note(message: str) -> None:
    """A ``note:`` line on stderr: what a user should know of how the command went."""
    console.print(f"[yellow]note:[/] {escape(message)}", soft_wrap=True)


def split_csv(value: str | None) -> list[str] | None:
    """``"a, b,"`` -> ``["a", "b"]``; None for an empty or absent option."""
    if not value:
        return None
    return [v.strip() for v in value.split(",") if v.strip()]
