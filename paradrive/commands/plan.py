"""``paradrive plan``: a build's pairs, media and intermediate bytes and CPU / GPU hours,
projected before it runs (:func:`paradrive.pipeline.budget.plan_build`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from paradrive.commands.common import DEFAULT_DATA, fail, new_console
from paradrive.errors import ConfigError, ParaDriveError

if TYPE_CHECKING:  # the plan's modules are imported when the command runs
    from paradrive.contracts.specs import ResolvedConfig
    from paradrive.pipeline.budget import Plan


def _size(value: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if value >= scale:
            return f"{value / scale:.2f} {unit}"
    return f"{value / 1e3:.1f} kB"


def print_plan(plan: Plan, config: ResolvedConfig, data_dir: Path, console: Console) -> None:
    """The plan's totals, the scenes that can give no clip and its rates, on ``console``."""
    summary = plan.as_json()
    known = ", ".join(f"{n} {how}" for how, n in sorted(plan.shapes.items()))
    console.print(f"plan: {plan.scenes} scene(s) ({known}), profile {config.profile}; rates measured "
                  f"on the finished scenes of {data_dir} where there are any, else stages/budget/rates.yaml",
                  markup=False)
    console.print(f"pairs         {plan.pairs:,}")
    console.print(f"media         {_size(summary['media_bytes'])} (the clips)")
    if summary["latent_bytes"]:
        console.print(f"latents       {_size(summary['latent_bytes'])} (encode: Wan2.1 VAE latents)")
    console.print(f"intermediate  {_size(summary['intermediate_bytes'])} at most, "
                  f"{_size(summary['intermediate_bytes_kept'])} kept after retention")
    console.print(f"compute       {summary['cpu_hours']:.2f} CPU-hours, "
                  f"{summary['gpu_hours']:.2f} GPU-hours")
    for scene_id, why in plan.unfit.items():
        console.print(f"no clip       scene {scene_id}: {why} (the build fails it after its ingest)",
                      markup=False)
    table = Table(title="rates", title_justify="left")
    for name in ("what", "total", "kept", "rate", "per", "source"):
        table.add_column(name, overflow="fold", justify="right" if name in ("total", "kept", "rate") else "left")
    for key, rate in plan.rates.items():
        kind, name = key.split(":", 1)
        if kind == "compute":
            table.add_row(f"{name} ({rate.device}-hours)", f"{plan.seconds[name] / 3600:.3f}", "",
                          f"{rate.value:.4g} s", rate.unit, escape(rate.source))
        else:
            table.add_row(name, _size(plan.bytes[name]), _size(plan.kept[name]),
                          f"{rate.value:.4g} B", rate.unit, escape(rate.source))
    console.print(table)


def plan_cmd(
    scene: list[str] = typer.Option([], "--scene", help="Scene URI. Repeatable."),
    scenes: list[str] = typer.Option([], "--scenes", help="A scene list file, a folder of logs, or "
                                                          "URIs (as for build). Repeatable."),
    profile: str | None = typer.Option(None, "--profile", "-p", help="Profile (stages/profiles/"
                                                                     "NAME.yaml); default: the paper's."),
    set_: list[str] = typer.Option([], "--set", help="Override a parameter: stage.param=value. Repeatable."),
    data: Path = typer.Option(DEFAULT_DATA, "--data", help="Data folder: its finished scenes give "
                                                           "measured rates, its ingested scenes their frames."),
    as_json: bool = typer.Option(False, "--json", help="Print the plan as JSON."),
) -> None:
    """Project pairs, media and intermediate bytes and CPU / GPU hours of a build, before it runs."""
    from paradrive.pipeline import StageRegistry, parse_overrides
    from paradrive.pipeline.budget import plan_build
    from paradrive.pipeline.build import default_selection
    from paradrive.pipeline.scenes import check_present, scene_uris

    try:
        config = StageRegistry().resolve(profile, parse_overrides(set_))
        given = scene_uris(scene, scenes)
        check_present(given, ingest=config.params.get("ingest"))   # a plan of logs that are not there projects nothing real
        uris = default_selection(config, given).uris
        if not uris:
            raise ConfigError("no scenes to plan: give --scene or --scenes")
        plan = plan_build(config, uris, data if data.is_dir() else None)
    except (ConfigError, ParaDriveError, ValueError) as exc:
        fail(str(exc))
    if as_json:
        print(json.dumps(plan.as_json(), indent=2))
    else:
        print_plan(plan, config, data, new_console())


def register(app: typer.Typer) -> None:
    """Add ``paradrive plan`` to the command line."""
    app.command("plan")(plan_cmd)
