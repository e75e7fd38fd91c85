"""The ``fit`` stage (``stages/fit.yaml``): a 3D Gaussian Splatting model of one scene, with
checkpoints at the configured iterations and ``gs/fit.json`` (:class:`FitRecord`).

The training itself is :func:`paradrive.gs.fit.fit_scene`; the typed parameters are
:class:`paradrive.contracts.params.FitParams`, which the fit takes too.
"""

from __future__ import annotations

from paradrive.contracts.base import StageContext
from paradrive.contracts.params import FitParams as Params
from paradrive.contracts.records import FitRecord


def run(ctx: StageContext[Params]) -> FitRecord:
    from paradrive.gs.fit import fit_scene
    from paradrive.stages.ingest import recorded_params

    threshold = recorded_params(ctx.layout).moving_threshold_m
    return fit_scene(ctx.layout, ctx.params, log=ctx.log, progress=ctx.progress,
                     moving_threshold_m=threshold)
