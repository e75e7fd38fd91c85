"""Scale cue: the camera's height above the road's triangulated points
(:func:`paradrive.ingest.sfm.fit_road_plane`), against the camera's known height.

Per frame range, the road points whose overhead camera lies there give the height (their mean
depth below it) with its standard error. The points are a biased ruler: on forward motion
structure from motion trades a small pitch of every camera against the direction of travel,
which lifts each point by its distance times that pitch, the same way for all of them, so the
scatter says nothing of it. ``bias`` is that bias's size (``ingest.video_road_points_bias``),
added in quadrature.
"""

from __future__ import annotations

import math

from paradrive.ingest.scalecue import ScaleCue
from paradrive.ingest.sfm import RoadPlane

NAME = "road points"


def measure(plane: RoadPlane | None, frames: tuple[int, int], height_m: float, *, bias: float,
            offset: int = 0, why: str = "", min_points: int = 12) -> ScaleCue:
    """The cue over kept frames ``frames`` (``offset``: the reconstruction's frame of kept frame
    0); ``plane`` None: no road plane was found (``why``)."""
    if plane is None:
        return ScaleCue(NAME, frames, None, why=why or "no road plane")
    found = plane.within(frames[0] + offset, frames[1] + offset, min_points)
    if found is None:
        return ScaleCue(NAME, frames, None,
                        why=f"fewer than {min_points} road points lie under the cameras there")
    height, error, count = found
    return ScaleCue(NAME, frames, height_m / height, math.hypot(error, bias),
                    figures={"points": count, "standard_error": error, "systematic": bias})
