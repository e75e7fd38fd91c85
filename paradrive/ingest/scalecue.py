"""The metric scale of a video's poses from several independent cues, by frame range.

Each cue (a module ``paradrive.ingest.scale_<cue>``) measures the scale, metres per model
unit, over a range of frames, with a relative uncertainty that holds its known biases as well
as its scatter, or says why it could not (:class:`ScaleCue`). :func:`combine` then:

1. **within each range**, weighs the cues that measured there by their inverse variances (in
   log scale). Where they disagree by more than their uncertainties allow (the chi-square per
   degree of freedom above one), the combined uncertainty is widened by the square root of it
   (the Birge ratio): the cues' own spread then counts as a bias. Where two cues lie more than
   ``max_sigma`` combined uncertainties apart, at least one of them is wrong and the range
   cannot say which: :class:`ScaleError`, naming the cues, the range and their figures;
2. **across the ranges**, keeps each range's own scale: SfM's scale drifts along a monocular
   sequence (12 % between the ends of a real 51-frame bend), so one scale for the whole path
   fits neither end; :func:`profile` gives each frame its scale, piecewise linear between the
   ranges' middles, and :func:`paradrive.ingest.sfm.without_drift` evens the path out with it.
   A range where one cue failed is carried by another; one where every cue failed takes the
   scale between its neighbours, its uncertainty widened by half the ranges' spread. The whole
   path's scale is the ranges' weighted by their lengths, its uncertainty theirs weighted the
   same way and summed (a cue's bias has one sign in every range), with the uncertainties
   common to every cue (the focal length's, where it was estimated) added in quadrature.

A clip is refused only where no range could be measured by any cue (:class:`ScaleError`
naming each cue's reason) or where cues disagree beyond their uncertainties; an uncertainty
above the ingest's limit is the reader's call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ScaleCue", "RangeScale", "CombinedScale", "ScaleError", "split_ranges", "combine",
           "format_range", "profile"]


class ScaleError(ValueError):
    """No scale: no cue measured any range, or cues disagree beyond their uncertainties."""


@dataclass(frozen=True)
class ScaleCue:
    """One cue's measurement over the kept frames ``frames`` (first, last, inclusive):
    ``scale`` metres per model unit (None: not measured, ``why`` says why), ``uncertainty`` its
    relative uncertainty (one sigma, biases included), what it measured (``figures``)."""

    name: str
    frames: tuple[int, int]
    scale: float | None
    uncertainty: float = math.inf
    why: str = ""
    figures: dict[str, Any] = field(default_factory=dict)

    def doc(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"cue": self.name, "frames": list(self.frames)}
        if self.scale is None:
            return {**doc, "measured": False, "why": self.why}
        return {**doc, "measured": True, "scale": self.scale, "uncertainty": self.uncertainty,
                **self.figures}


@dataclass(frozen=True)
class RangeScale:
    """The scale of one frame range from the cues that measured it (``cues``, all that were
    tried); ``birge``: the factor its uncertainty was widened by for their disagreement."""

    frames: tuple[int, int]
    scale: float | None
    uncertainty: float
    cues: tuple[ScaleCue, ...]
    birge: float = 1.0
    filled_in: bool = False

    @property
    def carried_by(self) -> list[str]:
        return [c.name for c in self.cues if c.scale is not None]

    def doc(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"frames": list(self.frames), "carried_by": self.carried_by,
                               "cues": [c.doc() for c in self.cues]}
        if self.scale is not None:
            doc.update(scale=self.scale, uncertainty=self.uncertainty, birge=self.birge,
                       filled_in=self.filled_in)
        return doc


@dataclass(frozen=True)
class CombinedScale:
    """The scale over the whole path, its relative uncertainty and that uncertainty's ``parts``
    (each relative: ``ranges``, the common ones by name, and ``between_ranges``, half the spread
    of the ranges' scales: the drift that a scale per range takes out, so recorded, not added)."""

    scale: float
    uncertainty: float
    parts: dict[str, float]
    ranges: tuple[RangeScale, ...]

    def weight_of(self, cue: str) -> float:
        """The share of the scale's weight that ``cue`` carried, over every range."""
        total, mine = 0.0, 0.0
        for r in self.ranges:
            for c in r.cues:
                if c.scale is not None:
                    w = 1.0 / c.uncertainty ** 2
                    total += w
                    mine += w if c.name == cue else 0.0
        return mine / total if total else 0.0

    def without(self, *names: str) -> float:
        """The uncertainty without the common parts ``names`` (in quadrature, as combined)."""
        return _total({k: v for k, v in self.parts.items() if k not in names})

    def doc(self) -> dict[str, Any]:
        return {"parts": dict(self.parts), "ranges": [r.doc() for r in self.ranges]}


def format_range(frames: tuple[int, int]) -> str:
    return f"frames {frames[0]}-{frames[1]}"


def split_ranges(frames: int, min_frames: int, max_ranges: int) -> list[tuple[int, int]]:
    """``frames`` kept frames cut into at most ``max_ranges`` consecutive ranges of at least
    ``min_frames`` each (inclusive (first, last)); one range where the clip is shorter."""
    count = max(1, min(max_ranges, frames // max(min_frames, 1)))
    edges = [round(k * frames / count) for k in range(count + 1)]
    return [(edges[k], edges[k + 1] - 1) for k in range(count)]


def _in_range(cues: list[ScaleCue], frames: tuple[int, int], max_sigma: float) -> RangeScale:
    mine = tuple(c for c in cues if c.frames == frames)
    measured = [c for c in mine if c.scale is not None and math.isfinite(c.uncertainty)
                and c.uncertainty > 0]
    if not measured:
        return RangeScale(frames, None, math.inf, mine)
    for k, a in enumerate(measured):
        for b in measured[k + 1:]:
            gap = abs(math.log(a.scale / b.scale))  # type: ignore[operator]
            allowed = max_sigma * math.hypot(a.uncertainty, b.uncertainty)
            if gap > allowed:
                raise ScaleError(
                    f"the scale's cues disagree over {format_range(frames)}: {a.name} gives "
                    f"{a.scale:.4g} m a unit (±{a.uncertainty:.1%}), {b.name} {b.scale:.4g} "
                    f"(±{b.uncertainty:.1%}), {gap:.1%} apart, more than {max_sigma:g} times "
                    f"their combined uncertainty ({allowed / max_sigma:.1%})")
    weights = [1.0 / c.uncertainty ** 2 for c in measured]
    logs = [math.log(c.scale) for c in measured]  # type: ignore[arg-type]
    mean = sum(w * x for w, x in zip(weights, logs)) / sum(weights)
    sigma = 1.0 / math.sqrt(sum(weights))
    birge = 1.0
    if len(measured) > 1:
        chi2 = sum(w * (x - mean) ** 2 for w, x in zip(weights, logs)) / (len(measured) - 1)
        birge = max(1.0, math.sqrt(chi2))
    return RangeScale(frames, math.exp(mean), sigma * birge, mine, birge)


def combine(cues: list[ScaleCue], ranges: list[tuple[int, int]], *,
            lengths: list[float] | None = None, common: dict[str, float] | None = None,
            max_sigma: float = 3.0) -> CombinedScale:
    """The scale of each of ``ranges`` from ``cues`` (each cue's ``frames`` one of the ranges)
    and over the whole path, ``lengths`` the ranges' path lengths in model units (equal where
    None), with ``common`` relative uncertainties shared by every cue (by name). ``max_sigma``:
    two cues further apart than this many combined uncertainties are a contradiction (three
    sigma: a chance of under 0.3 % where both uncertainties hold). Raises ScaleError (one line).

    A range no cue measured takes the scale between its measured neighbours (in log scale, by
    the ranges' order; the nearest one's beyond the ends) and their uncertainty widened by half
    the measured ranges' spread, the drift it may hide. The whole path's scale is the ranges'
    scales weighted by their lengths; its uncertainty their uncertainties weighted the same way
    and summed, not added in quadrature (a cue's bias has one sign in every range), with the
    common ones added in quadrature."""
    per_range = [_in_range(cues, r, max_sigma) for r in ranges]
    measured = [k for k, r in enumerate(per_range) if r.scale is not None]
    if not measured:
        reasons = "; ".join(f"{c.name} over {format_range(c.frames)}: {c.why}" for c in cues
                            if c.scale is None) or "no cue was tried"
        raise ScaleError(f"no cue measured the metric scale ({reasons})")
    logs = [math.log(per_range[k].scale) for k in measured]  # type: ignore[arg-type]
    spread = (max(logs) - min(logs)) / 2
    filled = []
    for k, r in enumerate(per_range):
        if r.scale is not None:
            filled.append(r)
            continue
        log = float(np.interp(k, measured, logs))
        near = min(measured, key=lambda m: abs(m - k))
        filled.append(RangeScale(r.frames, math.exp(log),
                                 math.hypot(per_range[near].uncertainty, spread), r.cues,
                                 filled_in=True))
    weights = np.asarray(lengths if lengths is not None else [1.0] * len(ranges), dtype=np.float64)
    weights = weights / weights.sum()
    scale = float(sum(w * r.scale for w, r in zip(weights, filled)))
    parts = {"ranges": float(sum(w * r.uncertainty for w, r in zip(weights, filled))),
             "between_ranges": spread}
    parts.update(common or {})
    return CombinedScale(scale, _total(parts), parts, tuple(filled))


def _total(parts: dict[str, float]) -> float:
    """The parts in quadrature, ``between_ranges`` left out (a scale per range takes it out)."""
    return math.sqrt(sum(v ** 2 for k, v in parts.items() if k != "between_ranges"))


def profile(combined: CombinedScale, frames: int) -> np.ndarray:
    """(frames,) each kept frame's scale over the whole path's: piecewise linear in log scale
    between the ranges' middles, constant beyond the first and the last."""
    middles = [0.5 * (r.frames[0] + r.frames[1]) for r in combined.ranges]
    logs = [math.log(r.scale / combined.scale) for r in combined.ranges]  # type: ignore[operator]
    return np.exp(np.interp(np.arange(frames), middles, logs))
