"""The ``manifest`` stage (``stages/manifest.yaml``, build-scoped): the sharded pair manifest
and its ``index.json`` over every scene whose clips are done, with the referenced videos linked
into the build. The row logic and the publishing are :mod:`paradrive.manifest`.

With ``min_heldout_psnr`` set, a scene whose fit's held-out PSNR (fit.json ``heldout``, written
when the fit held views out) is below it, or that has none, is left out with its reason, and
index.json records the threshold and those scenes (``heldout_filter``). With
``max_dynamic_fraction`` set, pairs whose target is masked as moving over a larger share of its
pixels (the ``dynamic_fraction`` column) are left out, and index.json records the threshold, the
rows and their clips (``dynamic_filter``).
"""

from __future__ import annotations

import logging
from pathlib import Path

from paradrive.errors import ParaDriveError, SceneError
from paradrive.io import no_room_named
from paradrive.manifest import (MediaFile, dynamic_filter, publish, read_clips, scene_rows,
                                staging_version)
from paradrive.contracts.base import BuildContext
from paradrive.contracts.params import ManifestParams as Params
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import FitRecord, IndexRecord


def build_manifest(build_dir: str | Path, scene_dirs: list[dict], params: Params, *,
                   fingerprint: str = "", build: str | None = None,
                   log: logging.Logger | None = None, selection: dict | None = None,
                   data_root: str | Path | None = None) -> IndexRecord:
    """Rows from every scene in ``scene_dirs`` ([{scene_id, scene_uri, scene_dir}]) published
    under ``build_dir`` as a new version. A scene whose clips cannot be used is skipped with its
    reason; no usable scene at all is an error. ``data_root``: the folder the scenes live in."""
    build = build or Path(build_dir).name
    if data_root is None:  # called without a runner: the folder the scene folders share
        roots = {Path(e["scene_dir"]).resolve().parent.parent for e in scene_dirs}
        data_root = roots.pop() if len(roots) == 1 else None
    with staging_version(build_dir, build, log) as staging:
        rows: list[dict] = []
        media: list[MediaFile] = []
        scenes, skipped, dropped = [], [], []
        for entry in sorted(scene_dirs, key=lambda s: s["scene_id"]):
            low = None
            try:
                low = heldout_below(entry, params.min_heldout_psnr)
                if low is not None:
                    raise low
                found = _scene(entry, staging, params)
            except SceneError as exc:
                skip = {"scene_id": entry["scene_id"], "scene_uri": entry.get("scene_uri", ""),
                        "reason": str(exc)}
                skipped.append(skip)
                if exc is low:
                    dropped.append(skip)
                if log is not None:
                    log.warning("manifest: skipped %s", exc)
                continue
            rows.extend(found[0])
            media.extend(found[1])
            scenes.append(found[2])
        if not rows:
            reasons = "; ".join(s["reason"] for s in skipped) or "no scenes given"
            raise ParaDriveError(f"build {build}: no usable scene, nothing published ({reasons})")
        held = (None if params.min_heldout_psnr is None else
                {"min_psnr": float(params.min_heldout_psnr), "dropped": dropped})
        rows, moving = dynamic_filter(rows, params.max_dynamic_fraction)
        if not rows:
            raise ParaDriveError(f"build {build}: every pair's dynamic_fraction is above "
                                 f"manifest.max_dynamic_fraction={params.max_dynamic_fraction:g}, "
                                 f"nothing published; raise it or set it to null")
        return publish(build_dir, rows, media, scenes=scenes, skipped=skipped, params=params,
                       fingerprint=fingerprint, build=build, log=log, selection=selection,
                       data_root=data_root, staging=staging, heldout_filter=held,
                       dynamic_filter=moving)


def heldout_below(entry: dict, min_psnr: float | None) -> SceneError | None:
    """Why the scene of ``entry`` falls below the held-out PSNR ``min_psnr`` (None: it passes,
    or there is no threshold); a fit.json that cannot be read raises."""
    if min_psnr is None:
        return None
    layout = SceneLayout(Path(entry["scene_dir"]))
    fit = FitRecord.load(layout.fit_json, entry["scene_id"])
    if fit.heldout is None:
        return SceneError(f"fit held no views out, so its held-out PSNR is unknown (the build "
                          f"asks at least {min_psnr:g} dB)", scene_id=entry["scene_id"],
                          path=layout.fit_json,
                          fix="fit with fit.holdout_every or fit.holdout_cameras, or publish "
                              "with manifest.min_heldout_psnr=null")
    if fit.heldout.psnr < min_psnr:
        return SceneError(f"held-out PSNR {fit.heldout.psnr:.2f} dB is below "
                          f"manifest.min_heldout_psnr {min_psnr:g} dB", scene_id=entry["scene_id"],
                          path=layout.fit_json, fix="left out of this build by its fit quality")
    return None


def _scene(entry: dict, staging: Path, params: Params) -> tuple[list[dict], list[MediaFile], dict]:
    """One scene's rows, media and summary; an inference build's truth views land in ``staging``."""
    truth = None
    if params.kind == "inference":
        from paradrive.inference import truth_renderer

        truth = truth_renderer(entry["scene_dir"], staging, read_clips(entry["scene_dir"]))
    rows, media, summary = scene_rows(entry["scene_dir"], verify_inputs=params.verify_inputs,
                                      quality=params.quality, truth=truth)
    summary["scene_uri"] = entry.get("scene_uri") or summary["scene_uri"]
    summary["scene_dir"] = entry.get("scene_location") or summary["scene_dir"]  # a URL root's own
    fit_json = SceneLayout(Path(entry["scene_dir"])).fit_json
    held = FitRecord.load(fit_json, entry["scene_id"]).heldout if fit_json.is_file() else None
    if held is not None:   # so a build's scenes sort by fit quality (paradrive inspect)
        summary.update(heldout_psnr=held.psnr, heldout_ssim=held.ssim)
    return rows, media, summary


def run(ctx: BuildContext[Params]) -> IndexRecord:
    # a publish that finds no room (a Parquet shard, a media copy) names the build folder
    with no_room_named(ctx.build_dir):
        return build_manifest(ctx.build_dir, ctx.scenes, ctx.params, fingerprint=ctx.fingerprint,
                              build=ctx.build, log=ctx.log, selection=ctx.selection,
                              data_root=ctx.data_dir)
