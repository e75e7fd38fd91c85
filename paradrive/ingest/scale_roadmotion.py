"""Scale cue: the camera's height from the road's own motion in the images
(:mod:`paradrive.ingest.roadmotion`), against the camera's known height above the road.

Per frame range, the pairs that start there give the height (their median) and its relative
uncertainty: the median's scatter, the drift along the range, the band between the near and
the far road, and the codec (how far one more encode of the frames moves it)
(:attr:`~paradrive.ingest.roadmotion.RoadMotion.uncertainty`). A range with too few pairs that
align is not measured by this cue.
"""

from __future__ import annotations

from paradrive.ingest.roadmotion import RoadMotion
from paradrive.ingest.scalecue import ScaleCue

NAME = "road motion"


def measure(motion: RoadMotion | None, frames: tuple[int, int], height_m: float, *,
            why: str = "", min_pairs: int = 5) -> ScaleCue:
    """The cue over kept frames ``frames`` from the road's motion over the whole run (None:
    it could not be measured at all, ``why``)."""
    if motion is None:
        return ScaleCue(NAME, frames, None, why=why or "fewer than 5 frame pairs aligned on the road")
    part = motion.within(frames[0], frames[1], min_pairs)
    if part is None:
        return ScaleCue(NAME, frames, None,
                        why=f"fewer than {min_pairs} frame pairs aligned on the road there")
    return ScaleCue(NAME, frames, height_m / part.height, part.uncertainty,
                    figures={"pairs": len(part.pairs), "scatter": part.scatter,
                             "drift": part.drift, "band": part.band, "codec": part.codec})
