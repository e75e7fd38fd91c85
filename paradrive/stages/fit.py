"""The ``fit`` stage (``stages/fit.yaml``): a 3D Gaussian Splatting model of one scene, with
checkpoints at the configured iterations and ``gs/fit.json`` (:class:`FitRecord`).

The training itself is :func:`paradrive.gs.fit.fit_scene`; the typed parameters are
:class:`paradrive.contracts.params.FitParams`, which the fit takes too. A fit that held views out
(``holdout_every`` / ``holdout_cameras``) records its final checkpoint's PSNR / SSIM on them in
fit.json (``heldout``), where publishing reads it (``manifest.min_heldout_psnr``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from paradrive.contracts.base import StageContext
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.params import FitParams as Params
from paradrive.contracts.records import FitRecord


def fit_scene(scene: SceneLayout | str | Path, params: Params, *, log: logging.Logger | None = None,
              progress: Callable[..., None] | None = None, stop_after: int | None = None,
              moving_threshold_m: float | None = None) -> FitRecord:
    """The fit of :func:`paradrive.gs.fit.fit_scene`, with its record written as ``gs/fit.json``
    at every checkpoint (what the later stages and a resumed build read)."""
    from paradrive.gs import fit as gsfit

    layout = SceneLayout.at(scene)
    return gsfit.fit_scene(layout, params, log=log, progress=progress, stop_after=stop_after,
                           moving_threshold_m=moving_threshold_m,
                           on_record=lambda record: record.save(layout.fit_json))


def run(ctx: StageContext[Params]) -> FitRecord:
    from paradrive.gs.init import Holdout
    from paradrive.contracts.params import recorded_params

    threshold = recorded_params(ctx.layout, ctx.build_params.get("ingest")).moving_threshold_m
    record = fit_scene(ctx.layout, ctx.params, log=ctx.log, progress=ctx.progress,
                       moving_threshold_m=threshold)
    if record.complete and Holdout.of(ctx.params).active:
        from paradrive.gs.views import heldout_record

        held = heldout_record(ctx.layout, ctx.params, record, threshold)
        ctx.log.info("fit: %s held out %d views: PSNR %.2f dB, SSIM %.4f at iteration %d",
                     record.scene_id, held.views, held.psnr, held.ssim, held.iteration)
        record = record.model_copy(update={"heldout": held})
        record.save(ctx.layout.fit_json)
    return record
