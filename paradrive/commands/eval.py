"""``paradrive eval``: a fitted scene measured against the truth (:mod:`paradrive.evaluation`),
or with ``--build`` and ``--videos`` an inference set's generated videos scored
(:mod:`paradrive.scoring`: the paper's table)."""

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


def _score_settings(metrics: str | None, weights: dict[str, Path | None], flow_weights: Path | None,
                    device: str, cache: Path | None, camera_stride: int | None):
    """The scoring settings the options ask for; ConfigError (exit 2) before any video is read
    for an unknown metric, a metric whose weights are not given, or weights that are not the
    network's. Without --metrics: the weight-free metrics and every one whose weights are given."""
    from dataclasses import replace

    from paradrive.scoring.camera import CameraSettings
    from paradrive.scoring.features import check_weights
    from paradrive.scoring.flow import FlowSettings
    from paradrive.scoring.run import WEIGHT_FREE, ScoreSettings

    if metrics:
        chosen = tuple(dict.fromkeys(m.strip().replace("-", "_") for m in metrics.split(",")
                                     if m.strip()))
    else:
        chosen = WEIGHT_FREE + tuple(m for m, p in weights.items() if p is not None)
    checked = tuple(check_weights(m, weights.get(m)) for m in chosen if m in weights)
    camera = CameraSettings() if camera_stride is None else replace(CameraSettings(),
                                                                    stride=camera_stride)
    flow = FlowSettings()
    if flow_weights is not None:
        from paradrive.scoring.raft import raft_settings

        flow = raft_settings(flow_weights)   # checked here, before any video is read
    return ScoreSettings(metrics=chosen, camera=camera, flow=flow, weights=checked, device=device,
                         cache=cache)


def _print_scores(doc: dict, out, title: str) -> None:
    from paradrive.scoring.table import paper_table

    for block in paper_table(doc):
        table = Table(title=escape(f"{block.title}: {title}"), title_justify="left")
        for i, heading in enumerate(block.headings):
            table.add_column(heading, justify="left" if i == 0 else "right", no_wrap=True)
        for line in block.lines:
            table.add_row(*line)
        out.print(table)


def score_build_cmd(build: Path | None, videos: Path | None, out_dir: Path | None,
                    options: dict, *, as_json: bool = False, csv_path: Path | None = None) -> None:
    """``paradrive eval --build B --videos V``: exit 0 all scored, 3 some missing or unreadable,
    2 none/usage."""
    import json

    from paradrive.errors import ParaDriveError
    from paradrive.io import write_json
    from paradrive.scoring.run import score_videos
    from paradrive.scoring.table import plot_scores, write_csv

    out, err = new_console(), new_console(stderr=True)
    if build is None or videos is None or not videos.is_dir():
        fail("--build takes an inference set and --videos a folder of generated videos named by pair_id",
             err=err, soft_wrap=False)
    folder = Path(out_dir) if out_dir is not None else videos
    try:
        settings = _score_settings(**options)
        doc = score_videos(build, videos, settings, out_dir=folder)
    except ParaDriveError as exc:
        fail(str(exc), err=err, soft_wrap=False)
    scored = [r for r in doc["rows"] if r["error"] is None]
    if not scored:
        why = f"; e.g. {doc['failed'][0]['error']}" if doc["failed"] else ""
        fail(f"no video in {videos} could be scored ({len(doc['missing'])} rows without a video, "
             f"{len(doc['failed'])} that could not be scored){why}", err=err, soft_wrap=False)
    folder.mkdir(parents=True, exist_ok=True)
    csv_path = csv_path or folder / "scores.csv"
    write_csv(doc, csv_path)
    plot_scores(doc, folder / "scores.png")
    write_json(folder / "scores.json", doc)
    if as_json:
        print(json.dumps(doc, indent=2))
    else:
        _print_scores(doc, out, f"{videos} against {build}")
        out.print(f"wrote {folder / 'scores.json'}, {csv_path} and {folder / 'scores.png'}",
                  markup=False)
    for what, items in (("have no video", doc["missing"]), ("could not be scored", doc["failed"])):
        if items:
            first = items[0] if isinstance(items[0], str) else f"{items[0]['pair_id']}: {items[0]['error']}"
            err.print(f"[yellow]{len(items)} row(s) {what}[/], e.g. {escape(str(first))}")
    if doc.get("skipped"):
        first = doc["skipped"][0]
        err.print(f"[yellow]note:[/] {len(doc['skipped'])} value(s) not measured, e.g. "
                  f"{escape(first['pair_id'])}: {escape(first['metric'])}: {escape(first['reason'])}")
    if doc["missing"] or doc["failed"]:
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
    metrics: str | None = typer.Option(None, "--metrics", help="With --build: comma-separated, of psnr (PSNR / SSIM where a true view exists), camera (RErr / TErr), tce, fid, fvd, clip_v, iq (default: psnr, camera, tce and each metric whose weights are given)."),
    fid_weights: Path | None = typer.Option(None, "--fid-weights", help="FID's Inception-v3 weights file (pt_inception-2015-12-05-6726825d.pth); never downloaded."),
    fvd_weights: Path | None = typer.Option(None, "--fvd-weights", help="FVD's I3D weights file (Kinetics-400 RGB I3D); never downloaded."),
    clip_weights: Path | None = typer.Option(None, "--clip-weights", help="CLIP-V's CLIP model folder (Hugging Face layout); never downloaded."),
    iq_weights: Path | None = typer.Option(None, "--iq-weights", help="IQ's MUSIQ weights file (VBench's imaging quality); never downloaded."),
    flow_weights: Path | None = typer.Option(None, "--flow-weights", help="TCE's flow from RAFT's original weights file (raft-things.pth, or raft-small.pth; SEA-RAFT's are refused), 12 iterations; never downloaded (default: OpenCV's DIS, no weights)."),
    device: str = typer.Option("auto", "--device", help="With --build: where the networks run (auto: CUDA when present)."),
    cache: Path | None = typer.Option(None, "--cache", help="With --build: the per-video results and features cache (default <out>/scores-cache)."),
    camera_stride: int | None = typer.Option(None, "--camera-stride", help="With --build: locate every n-th frame for RErr / TErr (default 4)."),
    as_json: bool = typer.Option(False, "--json", help="With --build: print the scores document as JSON instead of the table."),
    csv_path: Path | None = typer.Option(None, "--csv", help="With --build: the CSV of one line per video (default <out>/scores.csv)."),
) -> None:
    """Measure shifted renders against the synthetic street's true views, the condition renders against the recorded frames, and every checkpoint on the views the fit held out (any dataset).

    With --build and --videos: score generated novel-trajectory videos (the paper's table: RErr,
    TErr, TCE, FID, FVD, CLIP-V, IQ, and PSNR / SSIM where a true view exists) per offset and
    dataset; writes scores.json, scores.csv and scores.png (docs/evaluation.md).
    """
    if build is not None or videos is not None:
        weights = {"fid": fid_weights, "fvd": fvd_weights, "clip_v": clip_weights, "iq": iq_weights}
        score_build_cmd(build, videos, out_dir, dict(
            metrics=metrics, weights=weights, flow_weights=flow_weights, device=device, cache=cache,
            camera_stride=camera_stride), as_json=as_json, csv_path=csv_path)
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
