"""The ``paradrive`` command line."""

from __future__ import annotations

import importlib
import logging
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from paradrive import __version__
from paradrive.errors import ConfigError, ParaDriveError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Build parallel-trajectory video pairs from single-pass driving logs.")
console = Console(stderr=True)
out = Console()

DEFAULT_DATA = Path("data")
DEFAULT_MANIFESTS = Path("manifests")
DEFAULT_SCENE = "synthetic:demo?seed=7"


def fail(message: str, code: int = 2) -> None:
    console.print(f"[bold red]error:[/] {message}")
    raise typer.Exit(code)


def version_callback(value: bool) -> None:
    if value:
        out.print(f"paradrive {__version__}")
        raise typer.Exit()


@app.callback()
def main_callback(version: bool = typer.Option(False, "--version", callback=version_callback,
                                               is_eager=True, help="Print the version.")) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


def _split_csv(value: Optional[str]) -> Optional[list[str]]:
    if not value:
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def collect_scene_uris(scene: list[str], scenes: list[str]) -> list[str]:
    """URIs from --scene (one URI each) and --scenes (a list file, a folder of logs, or URIs)."""
    uris = list(scene)
    if scenes:
        from paradrive.pipeline.scenes import expand_scene_inputs

        uris.extend(expand_scene_inputs(scenes))
    return uris


@app.command()
def build(
    scene: List[str] = typer.Option([], "--scene", help="Scene URI, e.g. 'synthetic:demo?seed=7'. Repeatable."),
    scenes: List[str] = typer.Option([], "--scenes", help="A scene list file, a folder of logs, or URIs. Repeatable."),
    profile: Optional[str] = typer.Option(None, "--profile", "-p", help="Parameter profile (stages/profiles/NAME.yaml); default: the paper's."),
    stages: Optional[str] = typer.Option(None, "--stages", help="Comma-separated stages to run (default: all)."),
    data: Path = typer.Option(DEFAULT_DATA, "--data", help="Where scenes are written (<data>/scenes/<scene_id>)."),
    manifests: Path = typer.Option(DEFAULT_MANIFESTS, "--manifests", help="Where builds (pair manifests) are written."),
    build_name: str = typer.Option("default", "--build", help="Build name: manifests go to <manifests>/<build>."),
    executor: str = typer.Option("local", "--executor", help="local or ray."),
    address: Optional[str] = typer.Option(None, "--address", help="Ray cluster address (default: start a local one)."),
    set_: List[str] = typer.Option([], "--set", help="Override a parameter: stage.param=value. Repeatable."),
    force: bool = typer.Option(False, "--force", help="Redo stages even when their outputs are up to date."),
    retry_failed: bool = typer.Option(False, "--retry-failed", help="Run again only the scenes the ledger records as failed."),
) -> None:
    """Run the pipeline on one or many scenes; stages that are up to date are skipped."""
    from paradrive.pipeline import StageRegistry, parse_overrides
    from paradrive.pipeline.build import run_build
    from paradrive.pipeline.executors import make_executor

    try:
        uris = collect_scene_uris(scene, scenes) or ([] if retry_failed else [DEFAULT_SCENE])
        config = StageRegistry().resolve(profile, parse_overrides(set_))
        stage_list = _split_csv(stages)
        config.registry().order(stage_list)  # unknown stage names fail here
        ledger = _open_ledger(manifests, build_name)
        if retry_failed:
            uris = ledger.failed_scene_uris() if ledger else []
            if not uris:
                out.print("nothing to retry: the ledger records no failed scene")
                raise typer.Exit(0)
        options = {"address": address} if executor == "ray" else {}
        runner = make_executor(executor, **options)
    except (ConfigError, ParaDriveError, ValueError) as exc:
        fail(str(exc))

    report = _run_with_progress(config, uris, data, stage_list, runner, manifests, build_name,
                                force, ledger)
    _print_report(report)
    raise typer.Exit(report.exit_code)


def _open_ledger(manifests: Path, build_name: str):
    try:
        from paradrive.pipeline.ledger import Ledger
    except ModuleNotFoundError:
        return None
    return Ledger.for_build(manifests, build_name)


def _run_with_progress(config, uris, data, stage_list, runner, manifests, build_name, force, ledger):
    from paradrive.pipeline.build import run_build, split_stages

    scene_stages, build_stages = split_stages(config, stage_list)
    total = len(uris) * len(scene_stages) + len(build_stages)
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TimeElapsedColumn(), TimeRemainingColumn(), console=console,
                        transient=False, disable=not console.is_terminal)
    failed = 0

    def on_start(scene_id: str, stage: str) -> None:
        progress.update(task, description=f"{stage:<8} {scene_id}")
        if ledger:
            ledger.start(scene_id, stage)

    def on_result(result) -> None:
        nonlocal failed
        failed += result.status in ("failed", "blocked")
        progress.advance(task)
        progress.update(task, description=f"{result.stage:<8} {result.scene_id} {result.status}"
                                          + (f" ({failed} failed)" if failed else ""))
        if ledger:
            ledger.record(result)
        style = {"done": "green", "skipped": "dim", "failed": "red", "blocked": "yellow"}[result.status]
        console.print(f"[{style}]{result.status:>7}[/] {result.stage:<8} {result.scene_id}"
                      + (f" — {result.error}" if result.error else f" ({result.seconds:.1f} s)"))

    with progress:
        task = progress.add_task("starting", total=total)
        if ledger:
            ledger.register(uris, scene_stages)
        return run_build(config, uris, data, stages=stage_list, executor=runner,
                         manifests_dir=manifests, build=build_name, force=force,
                         on_start=on_start, on_result=on_result)


def _print_report(report) -> None:
    scenes = report.scenes()
    done = sum(1 for s in scenes.values() if s == "done")
    table = Table(title="build summary", show_lines=False)
    table.add_column("scene")
    table.add_column("status")
    table.add_column("reason", overflow="fold")
    reasons = {r.scene_id: r.error for r in report.failures()}
    for sid, state in scenes.items():
        table.add_row(sid, "[green]done" if state == "done" else "[red]failed", reasons.get(sid, ""))
    for r in report.results:
        if r.scene_id.startswith("build:"):
            table.add_row(r.scene_id, r.status, r.error)
    out.print(table)
    out.print(f"{done} of {len(scenes)} scenes done"
              + ("" if report.exit_code == 0 else f"; exit code {report.exit_code} "
                 f"({'partial build' if report.exit_code == 3 else 'failed'})"))


@app.command("stages")
def stages_cmd(
    profile: Optional[str] = typer.Option(None, "--profile", "-p", help="Show values under this profile."),
    set_: List[str] = typer.Option([], "--set", help="Override: stage.param=value."),
    stage: Optional[str] = typer.Argument(None, help="Only this stage."),
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
        table.add_column("from")
        table.add_column("why / source", overflow="fold")
        for key, param in spec.params.items():
            origin = config.origins[name][key]
            value = config.params[name][key]
            table.add_row(key, repr(value), origin if origin == "default" else f"[yellow]{origin}",
                          param.doc)
        out.print(table)
    out.print(f"profiles: paper (defaults), {', '.join(registry.profiles())}")


# Commands that live next to the code they drive. Each module exposes ``register(app)``.
COMMAND_MODULES = [
    ("paradrive.inspect", "inspect"),
    ("paradrive.eval", "eval"),
    ("paradrive.pipeline.status", "status"),
    ("paradrive.train.cli", "train"),
]


def _register_commands() -> None:
    for module_name, command in COMMAND_MODULES:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if not (exc.name and module_name.startswith(exc.name)):
                raise
            _register_missing(command, module_name)
            continue
        module.register(app)


def _register_missing(command: str, module_name: str) -> None:
    @app.command(command, context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
                 help=f"(not available in this installation: {module_name} is missing)")
    def _missing() -> None:
        fail(f"'paradrive {command}' is not available: {module_name} is not installed")


_register_commands()


def main() -> None:
    try:
        app()
    except ConfigError as exc:
        console.print(f"[bold red]error:[/] {exc}")
        sys.exit(2)


if __name__ == "__main__":
    main()
