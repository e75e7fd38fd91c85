"""``paradrive eval``: a fitted scene measured against the truth (:mod:`paradrive.evaluation`),
or with ``--build`` and ``--videos`` generated videos scored against an inference set's true
views (:mod:`paradrive.inference`)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from paradrive.commands.common import DEFAULT_SCENE, fail, new_console
from paradrive.errors import ConfigError, SceneError


def eval_table(doc: dict) -> Table:
    """A table of one eval document."""
    table = Table(title=f"eval {doc['scene_id']}", title_justify="left",
                  caption="vs: recorded = the recorded frames, truth = the street's true shifted "
                          "view; depth = median |relative| z-depth error (non-sky), signed = "
                          "median signed one (< 0: too near)")
    numeric = ("iter", "PSNR", "SSIM", "depth", "signed")
    for col in ("camera", "stream") + numeric[:1] + ("vs",) + numeric[1:]:
        table.add_column(col, justify="right" if col in numeric else "left", no_wrap=True)

    def fmt(x, spec):
        return "-" if x is None else format(x, spec)

    def row(cam, stream, r, vs):
        table.add_row(cam, stream, str(r["iteration"]), vs, fmt(r["psnr"], ".2f"),
                      fmt(r["ssim"], ".4f"), fmt(r.get("depth_abs_rel"), ".3f"),
                      fmt(r.get("depth_signed_rel"), "+.3f"))

    for cam, c in doc["cameras"].items():
        for r in c["conditions"]:
            row(cam, r["stream"], r, "recorded")
        row(cam, "recorded", c["recorded"], "recorded")
        for r in sorted(c["shifted"], key=lambda r: (abs(r["offset_m"]), -r["offset_m"])):
            row(cam, r["stream"], r, "truth")
    for cam, c in doc.get("heldout", {}).get("per_camera", {}).items():
        for r in c["checkpoints"]:
            row(cam, f"heldout {c['kind']}", r, "held out")
    return table


def score_build_cmd(build: Path | None, videos: Path | None, out_dir: Path | None) -> None:
    """``paradrive eval --build B --videos V``: exit 0 all scored, 3 some missing, 2 none/usage."""
    from paradrive.errors import ParaDriveError
    from paradrive.inference import plot_scores, score_videos
    from paradrive.io import write_json

    out, err = new_console(), new_console(stderr=True)
    if build is None or videos is None or not videos.is_dir():
        fail("--build takes an inference set and --videos a folder of generated videos named by pair_id",
             err=err, soft_wrap=False)
    try:
        doc = score_videos(build, videos)
    except ParaDriveError as exc:
        fail(str(exc), err=err, soft_wrap=False)
    if not doc["rows"]:
        fail(f"no video in {videos} matches a row with a target ({len(doc['missing'])} missing, "
             f"{doc['rows_without_target']} rows without a true view)", err=err, soft_wrap=False)
    folder = Path(out_dir) if out_dir is not None else videos
    folder.mkdir(parents=True, exist_ok=True)
    plot_scores(doc, folder / "scores.png")
    write_json(folder / "scores.json", doc)
    table = Table(title=escape(f"{videos} against {build}"), title_justify="left")
    for col in ("offset", "videos", "PSNR", "SSIM"):
        table.add_column(col, justify="right")
    for r in doc["by_offset"]:
        table.add_row(f"{r['offset_m']:+g} m", str(r["videos"]), f"{r['psnr']:.2f}",
                      f"{r['ssim']:.4f}")
    out.print(table)
    out.print(f"wrote {folder / 'scores.json'} and {folder / 'scores.png'}", markup=False)
    if doc["missing"]:
        err.print(f"[yellow]{len(doc['missing'])} row(s) have no video[/], e.g. "
                      f"{escape(str(doc['missing'][0]))}")
        raise typer.Exit(3)


def eval_cmd(
    scene: list[str] = typer.Option([], "--scene", help="Scene URI, e.g. 'synthetic:demo?seed=7'; a real log's scene is measured on the views its fit held out. Repeatable."),
    data: str = typer.Option("data", "--data", help="Where scenes live (<data>/scenes/<scene_id>): a folder, or the URL a build wrote to (the scene is copied to the cache first)."),
    profile: str | None = typer.Option(None, "--profile", "-p", help="Parameter profile the scene was built with."),
    set_: list[str] = typer.Option([], "--set", help="Override a parameter: stage.param=value. Repeatable."),
    out_dir: Path | None = typer.Option(None, "--out", help="Write eval.json / eval.png here (default <scene>/eval; one scene)."),
    camera: str | None = typer.Option(None, "--camera", help="Comma-separated cameras (default: render.cameras)."),
    frames: int = typer.Option(16, "--frames", help="Evaluate at most this many evenly spaced clip frames (0 = all)."),
    build: Path | None = typer.Option(None, "--build", help="Score generated videos against an inference set's true views instead (with --videos)."),
    videos: Path | None = typer.Option(None, "--videos", help="With --build: a folder of generated videos, one per row, <pair_id>.mp4 (a pair id's '/' are folders)."),
) -> None:
    """Measure shifted renders against the synthetic street's true views, the condition renders against the recorded frames, and every checkpoint on the views the fit held out (any dataset).

    With --build and --videos: score generated novel-trajectory videos against the true
    views of a synthetic inference set (PSNR / SSIM per offset, scores.json and scores.png).
    """
    if build is not None or videos is not None:
        score_build_cmd(build, videos, out_dir)
        return

    from paradrive.evaluation import evaluate_scene
    from paradrive.pipeline import StageRegistry, parse_overrides
    from paradrive.storage import DataRoot, local_scene
    from paradrive.uri import parse_uri

    out, err = new_console(), new_console(stderr=True)
    uris = list(scene) or [DEFAULT_SCENE]
    try:
        config = StageRegistry().resolve(profile, parse_overrides(set_))
        parsed = [parse_uri(u) for u in uris]
    except ConfigError as exc:
        fail(str(exc), err=err, soft_wrap=False)
    if out_dir is not None and len(uris) > 1:
        fail("--out takes one --scene", err=err, soft_wrap=False)
    failed = 0
    for uri in parsed:
        try:
            scene_dir = local_scene(DataRoot.of(data), uri.scene_id)
            doc = evaluate_scene(scene_dir, config.typed("render"),
                                 ingest_params=config.params["ingest"],
                                 cameras=[c.strip() for c in camera.split(",")] if camera else None,
                                 max_frames=frames or None, out_dir=out_dir,
                                 fit_params=config.typed("fit"))
        except (SceneError, ConfigError) as exc:
            err.print(f"[bold red]error:[/] {escape(str(exc))}")
            failed += 1
            continue
        out.print(eval_table(doc))
        where = Path(out_dir) if out_dir else scene_dir / "eval"
        out.print(f"wrote {where / 'eval.json'} and {where / 'eval.png'}", markup=False)
    if failed:
        raise typer.Exit(2 if failed == len(parsed) else 3)


def register(app: typer.Typer) -> None:
    """Add ``paradrive eval`` to the command line."""
    app.command("eval")(eval_cmd)
