"""The ``manifest`` stage (``stages/manifest.yaml``, build-scoped): the sharded pair manifest
and its ``index.json`` over every scene whose clips are done, with the referenced videos linked
into the build. The row logic and the publishing are :mod:`paradrive.manifest`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from paradrive.errors import ParaDriveError, SceneError
from paradrive.manifest import MediaFile, publish, read_clips, scene_rows
from paradrive.contracts.base import BuildContext, StageParams
from paradrive.contracts.records import IndexRecord


class Params(StageParams):
    shard_rows: int
    shard_bytes: int | None
    row_group_rows: int
    compression: str
    media: str
    verify_inputs: bool
    quality: bool
    kind: str
    exclude_splits: list[str]


def build_manifest(build_dir: str | Path, scene_dirs: list[dict], params: Params, *,
                   fingerprint: str = "", build: str | None = None,
                   log: logging.Logger | None = None, selection: dict | None = None) -> IndexRecord:
    """Rows from every scene in ``scene_dirs`` ([{scene_id, scene_uri, scene_dir}]) published
    under ``build_dir``. A scene whose clips cannot be used is skipped with its reason; no usable
    scene at all is an error."""
    rows: list[dict] = []
    media: list[MediaFile] = []
    scenes, skipped = [], []
    for entry in sorted(scene_dirs, key=lambda s: s["scene_id"]):
        try:
            truth = None
            if params.kind == "inference":
                from paradrive.inference import truth_renderer

                truth = truth_renderer(entry["scene_dir"], build_dir, read_clips(entry["scene_dir"]))
            scene_rows_, scene_media, summary = scene_rows(
                entry["scene_dir"], verify_inputs=params.verify_inputs, quality=params.quality,
                truth=truth)
        except SceneError as exc:
            skipped.append({"scene_id": entry["scene_id"], "scene_uri": entry.get("scene_uri", ""),
                            "reason": str(exc)})
            if log is not None:
                log.warning("manifest: skipped %s", exc)
            continue
        summary["scene_uri"] = entry.get("scene_uri") or summary["scene_uri"]
        summary["scene_dir"] = entry.get("scene_location") or summary["scene_dir"]  # a URL root's own
        rows.extend(scene_rows_)
        media.extend(scene_media)
        scenes.append(summary)
    if not rows:
        reasons = "; ".join(s["reason"] for s in skipped) or "no scenes given"
        raise ParaDriveError(f"build {build or Path(build_dir).name}: no usable scene, nothing "
                             f"published ({reasons})")
    return publish(build_dir, rows, media, scenes=scenes, skipped=skipped, params=params,
                   fingerprint=fingerprint, build=build, log=log, selection=selection)


def run(ctx: BuildContext[Params]) -> IndexRecord:
    return build_manifest(ctx.build_dir, ctx.scenes, ctx.params, fingerprint=ctx.fingerprint,
                          build=ctx.build, log=ctx.log, selection=ctx.selection)
