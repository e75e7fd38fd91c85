"""Log readers: ``paradrive.ingest.<kind>.read(uri, out_dir, params, scene_id) -> Scene``
(``synthetic``, ``waymo``, ``nuscenes``, ``drivestudio``), and the camera choice they share.
The ingest stage itself is :mod:`paradrive.stages.ingest`.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from paradrive.errors import SceneError

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

log = logging.getLogger("paradrive.ingest")


def requested_cameras(params: IngestParams, dataset: str, *, scene_id: str) -> list[str] | None:
    """The cameras ``ingest.cameras`` asks for in a log of ``dataset`` (None = all the log has).

    ``auto`` is the dataset's fit set, ``ingest.camera_sets[dataset]`` (stages/ingest.yaml).
    """
    wanted = params.cameras
    if wanted is None or isinstance(wanted, (list, tuple)):
        return None if wanted is None else list(wanted)
    if wanted != "auto":
        raise SceneError(f"ingest.cameras = {wanted!r} is neither auto, null nor a list of cameras",
                         scene_id=scene_id, fix="set ingest.cameras to auto or e.g. [front]")
    sets = params.camera_sets
    if dataset not in sets:
        raise SceneError(f"ingest.cameras is auto but ingest.camera_sets has no {dataset} entry "
                         f"(has: {', '.join(sets) or 'none'})", scene_id=scene_id,
                         fix=f"add camera_sets.{dataset} to stages/ingest.yaml or list the "
                             f"cameras in ingest.cameras")
    return list(sets[dataset])


def select_cameras(available, params: IngestParams, dataset: str, *, scene_id: str, where) -> list[str]:
    """The cameras to ingest (``requested_cameras``) among ``available``, the log's. A camera
    listed in ``ingest.cameras`` must be there; ``auto`` takes the cameras of the fit set that
    the log has (a one-camera folder fits its one camera), says which it left out, and fails
    only where the log has none of them."""
    wanted = requested_cameras(params, dataset, scene_id=scene_id)
    if wanted is None:
        return list(available)
    missing = [c for c in wanted if c not in available]
    if missing and params.cameras == "auto" and len(missing) < len(wanted):
        kept = [c for c in wanted if c in available]
        log.warning("scene %s (%s): ingest.cameras is auto, the %s fit set (%s); the log has no "
                    "%s, so the fit sees %s", scene_id, where, dataset, ", ".join(wanted),
                    ", ".join(missing), ", ".join(kept))
        return kept
    if missing:
        asked = (f"ingest.cameras is auto, the {dataset} fit set (ingest.camera_sets.{dataset})"
                 if params.cameras == "auto" else "ingest.cameras asks for them")
        keep = [c for c in wanted if c in available] or list(available)
        raise SceneError(f"calibration missing for camera(s) {', '.join(missing)} "
                         f"(log has: {', '.join(available) or 'none'}; {asked})",
                         scene_id=scene_id, path=where,
                         fix=f"ingest the cameras the log has, e.g. --set "
                             f"ingest.cameras=[{','.join(keep)}]")
    return list(wanted)
