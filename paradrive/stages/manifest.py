"""The ``manifest`` stage (``stages/manifest.yaml``, build-scoped): the sharded pair manifest
and its ``index.json`` over every scene whose clips are done, with the referenced videos linked
into the build. The row logic and the publishing are :mod:`paradrive.manifest`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from paradrive.errors import ParaDriveError, SceneError
from paradrive.manifest import MediaFile, publish, read_clips, scene_rows, staging_version
from paradrive.contracts.base import BuildContext
from paradrive.contracts.params import ManifestParams as Params
from paradrive.contracts.records import IndexRecord


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
    with staging_version(build_dir, build) as staging:
        rows: list[dict] = []
        media: list[MediaFile] = []
        scenes, skipped = [], []
        for entry in sorted(scene_dirs, key=lambda s: s["scene_id"]):
            try:
                found = _scene(entry, staging, params)
            except SceneError as exc:
                skipped.append({"scene_id": entry["scene_id"],
                                "scene_uri": entry.get("scene_uri", ""), "reason": str(exc)})
                if log is not None:
                    log.warning("manifest: skipped %s", exc)
                continue
            rows.extend(found[0])
            media.extend(found[1])
            scenes.append(found[2])
        if not rows:
            reasons = "; ".join(s["reason"] for s in skipped) or "no scenes given"
            raise ParaDriveError(f"build {build}: no usable scene, nothing published ({reasons})")
        return publish(build_dir, rows, media, scenes=scenes, skipped=skipped, params=params,
                       fingerprint=fingerprint, build=build, log=log, selection=selection,
                       data_root=data_root, staging=staging)


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
    return rows, media, summary


def run(ctx: BuildContext[Params]) -> IndexRecord:
    return build_manifest(ctx.build_dir, ctx.scenes, ctx.params, fingerprint=ctx.fingerprint,
                          build=ctx.build, log=ctx.log, selection=ctx.selection,
                          data_root=ctx.data_dir)
