"""``paradrive stages``: the stages, their parameters, values and where each value comes from."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from paradrive.commands.common import fail, out
from paradrive.errors import ConfigError


def stages_cmd(
    profile: str | None = typer.Option(None, "--profile", "-p", help="Show values under this profile."),
    set_: list[str] = typer.Option([], "--set", help="Override: stage.param=value."),
    stage: str | None = typer.Argument(None, help="Only this stage."),
) -> None:
    """List the stages, their parameters, values and where each value comes from."""
    from paradrive.pipeline import StageRegistry, parse_overrides

    try:
        registry = StageRegistry()
        config = registry.resolve(profile, parse_overrides(set_))
        names = registry.order([stage] if stage else None)
    except ConfigError as exc:
        fail(str(exc))
    for name in names:
        spec = registry.specs[name]
        res = spec.resources
        table = Table(title=f"{name} [dim]({Path(spec.file).name}; needs: {', '.join(spec.needs) or '-'}; "
                            f"{spec.scope}; cpu {res.cpu:g}, gpu {res.gpu:g}, {res.memory_gb:g} GB)[/]",
                      title_justify="left")
        table.add_column("parameter")
        table.add_column("value")
        table.add_column("allowed", overflow="fold")
        table.add_column("from")
        table.add_column("why / source", overflow="fold")
        for key, param in spec.params.items():
            origin = config.origins[name][key]
            value = config.params[name][key]
            allowed = param.allowed() + (", or null" if param.default is None or param.nullable else "")
            table.add_row(key, escape(repr(value)), escape(allowed),
                          origin if origin == "default" else f"[yellow]{escape(origin)}", escape(param.doc))
        out.print(table)
    out.print(f"profiles: paper (defaults), {', '.join(registry.profiles())}", markup=False)


def register(app: typer.Typer) -> None:
    """Add ``paradrive stages`` to the command line."""
    app.command("stages")(stages_cmd)
