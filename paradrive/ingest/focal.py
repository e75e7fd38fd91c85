"""The focal length of a camera nobody calibrated, from its frames (structure from motion).

Refining the focal length inside bundle adjustment from a guess loses a forward-moving sequence:
the focal trades against the depth of everything seen ahead, and the refinement drifts to a
focal several times the truth and registers a handful of frames. Holding a pinhole's focal
fixed keeps the sequence at any focal in a wide range; what tells the candidates apart is how
well the model explains the images. On a bend that is sharp: a wrong focal cannot make the
rotation seen in the image agree with the parallax, and the mean reprojection error has its
minimum at the true focal. On a straight drive it is not: pure forward motion reconstructs
equally well at any focal (the scene is stretched along the road by the focal's error), and the
error's curve is flat.

:func:`estimate_focal` therefore matches the frames once (features and matches do not depend on
the focal) and maps them with the focal held fixed at candidates spread over the fields of
view dashcams have, then narrows in around the best; a parabola through the best trials in
``log f`` places the minimum. A trial that registers too few frames, or triangulates far fewer
points than the others (it dropped part of the scene, and its error is that of an easier
part), counts as failed. The focal counts as *observable* only where the coarse trials form one
basin (falling to a minimum inside the range searched, rising after it) and a focal one coarse
step from the best costs at least ``min_rise`` of the error: a gentle curve, like a straight
drive, gives a curve that is flat or jumps between reconstructions, and the estimate is then
only a guess (:attr:`FocalEstimate.observable` False: the caller counts the whole range
searched as the focal's uncertainty, and the clip is mapped with the focal held at the range's
middle in ``log f``, :attr:`FocalEstimate.held`).

What a wrong focal does (measured on the synthetic street, whose depth is known): mapped with
the focal held ``k`` times the truth, every depth comes out ``k`` times the truth while the
pixels' rays are ``1/k`` as wide, so every lateral and vertical offset keeps its true size and
only the lengths along the line of sight are stretched. The camera's height therefore scales
the reconstruction correctly across the road whatever the focal, and an error in the focal is
the same error in the lengths along it (the path, the speed): the scale's uncertainty along the
road includes the focal's, the one across the road does not (:mod:`paradrive.ingest.video`).

Its uncertainty (relative, one sigma) is the largest of three figures: the standard error of
the parabola's vertex given the scatter of the trials about it; half the difference between
the vertices the first and the second half of the frames give on their own, where both do
(each half is a separate stretch of road: what makes one focal fit better there than
elsewhere, a principal point off the centre, a lens with a little distortion, shows as their
disagreement); and half the finest step between trials. An error in the focal is the same
error in every length measured with the camera's height as the ruler (the reconstruction is
stretched along the road by it), so the scale's uncertainty includes it
(:mod:`paradrive.ingest.video`).

Nothing here knows a scene folder; errors are :class:`~paradrive.ingest.sfm.SfmError`.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from paradrive.ingest.sfm import Intrinsics, SfmError, extract_features, mapping_options

__all__ = ["FocalTrial", "FocalEstimate", "estimate_focal", "focal_of_fov", "FOV_RANGE_DEG"]

# the horizontal fields of view searched (degrees): a dashcam's lens lies between a narrow
# 30 deg (a telephoto mount, rare) and 120 deg (the widest rectilinear dashcams; wider ones are
# fisheyes, which a pinhole does not model)
FOV_RANGE_DEG = (30.0, 120.0)


def focal_of_fov(width: int, fov_deg: float) -> float:
    """The focal length (pixels) of a ``width``-pixel image with a horizontal field of view."""
    return 0.5 * width / math.tan(math.radians(fov_deg) / 2)


def searched_range(width: int) -> tuple[float, float]:
    """The smallest and the largest focal searched (pixels) for ``width``-pixel images: those
    of the widest and the narrowest field of view in :data:`FOV_RANGE_DEG`."""
    return focal_of_fov(width, FOV_RANGE_DEG[1]), focal_of_fov(width, FOV_RANGE_DEG[0])


@dataclass(frozen=True)
class FocalTrial:
    """One mapping with the focal held fixed: the focal (pixels at the SfM size), the frames
    it registered, its mean reprojection error (pixels; inf where no model formed) and seconds."""

    focal: float
    registered: int
    error: float
    seconds: float
    points: int = 0


@dataclass(frozen=True)
class FocalEstimate:
    """The focal length found (pixels at the size searched at, ``width`` pixels wide), its
    relative uncertainty (one sigma), whether the frames constrain it at all, the halves' own
    estimates, every trial."""

    focal: float
    uncertainty: float
    observable: bool
    rise: float
    halves: tuple[float | None, float | None]
    trials: tuple[FocalTrial, ...]
    frames: int
    seconds: float
    width: int

    @property
    def held(self) -> float:
        """The focal the clip is mapped with: the estimate where the frames constrain it, else
        the middle of the range searched (in ``log f``: any focal searched is as likely)."""
        return self.focal if self.observable else self.prior

    @property
    def prior(self) -> float:
        """The middle of the range searched, in ``log f``, at the size searched at."""
        return math.sqrt(self.prior_range[0] * self.prior_range[1])

    @property
    def prior_range(self) -> tuple[float, float]:
        """The smallest and the largest focal searched (pixels at the size searched at)."""
        return searched_range(self.width)

    @property
    def scale_uncertainty(self) -> float:
        """The focal's relative uncertainty as that of lengths along the road: its own where
        the frames constrain it, else half the searched range in ``log f``."""
        if self.observable:
            return self.uncertainty
        low, high = self.prior_range
        return math.log(high / low) / 2

    def intrinsics(self, width: int, height: int) -> Intrinsics:
        """The pinhole at ``width`` x ``height`` (the size searched at) with the :attr:`held`
        focal, principal point at the centre (pixel centres at +0.5)."""
        return Intrinsics(self.held, self.held, 0.5 * width, 0.5 * height)

    def doc(self) -> dict:
        """What ``scene.json`` records under ``video.intrinsics.focal_search``."""
        return {"focal_px": self.focal, "held_px": self.held, "uncertainty": self.uncertainty,
                "scale_uncertainty": self.scale_uncertainty,
                "observable": self.observable, "rise": self.rise,
                "halves_px": list(self.halves), "frames": self.frames, "seconds": self.seconds,
                "trials": [[t.focal, t.registered, t.error, t.points] for t in self.trials]}


def estimate_focal(image_dir: Path, names: list[str], work_dir: Path, size: tuple[int, int], *,
                   max_frames: int, min_rise: float, coarse: int = 5,
                   refine: tuple[float, ...] = (1.2, 1.1, 1.05), min_registered: float = 0.8,
                   seed: int = 0) -> FocalEstimate:
    """The focal length of the images ``names`` (in time order, all ``size`` = (width, height))
    under ``image_dir``; scratch files in ``work_dir`` (removed after).

    At most ``max_frames`` frames are used, evenly spaced over the sequence (each mapping costs
    seconds; a focal is a property of the lens, not of the whole clip). ``coarse`` focals
    log-spaced over :data:`FOV_RANGE_DEG` first, then around the best one at each ratio of
    ``refine``. A trial that registers under ``min_registered`` of the frames counts as failed:
    its error is that of a smaller, easier model. ``min_rise``: the relative rise of the error
    one coarse step from the best below which the focal counts as unobservable
    (``ingest.video_focal_min_rise``).

    Raises SfmError where no focal forms a model.
    """
    start = time.perf_counter()
    step = max(1, math.ceil(len(names) / max_frames))
    used = list(names[::step])
    work_dir.mkdir(parents=True, exist_ok=True)
    try:
        database = _matched(image_dir, used, work_dir, size, seed)
        trials, grid = _search(database, image_dir, used, work_dir, size, coarse, refine,
                               min_registered, seed)
        basin = _one_basin(grid)
        halves = tuple(_half_vertex(database, image_dir, used, work_dir, size, part,
                                    _vertex(trials)[0], min_registered, seed) if basin else None
                       for part in (0, 1))
    finally:
        shutil.rmtree(work_dir, ignore_errors=True)
    focal, spread = _vertex(trials)
    best = min(trials, key=lambda t: t.error)
    low, high = searched_range(size[0])
    ratio = (high / low) ** (1.0 / (coarse - 1))
    rise = _rise(trials, best, ratio)
    found = [h for h in halves if h is not None]
    disagreement = abs(math.log(found[0] / found[1])) / 2 if len(found) == 2 else 0.0
    # the finest trials lie refine[-1] apart: the vertex between them is taken as good to half
    # that step, whatever the parabola's own figure says
    floor = math.log(refine[-1]) / 2
    return FocalEstimate(focal=focal, uncertainty=float(max(spread, disagreement, floor)),
                         observable=bool(rise >= min_rise and basin), rise=rise,
                         halves=(halves[0], halves[1]), trials=tuple(trials), frames=len(used),
                         seconds=time.perf_counter() - start, width=size[0])


def _matched(image_dir: Path, names: list[str], work_dir: Path, size: tuple[int, int],
             seed: int) -> Path:
    """A database of the images' features and sequential matches, verified without a focal
    (the fundamental matrix), so that every candidate focal maps the same matches."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    pycolmap.set_random_seed(seed)
    database = work_dir / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    f = focal_of_fov(size[0], 60.0)
    reader.camera_params = ",".join(repr(float(v)) for v in (f, f, 0.5 * size[0], 0.5 * size[1]))
    extraction, matching, pairing, _ = mapping_options(True, seed)
    extract_features(database, image_dir, names, reader, extraction)
    _set_camera(database, None, size)
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                              device=pycolmap.Device.cpu)
    return database


def _set_camera(database: Path, focal: float | None, size: tuple[int, int]) -> None:
    """The database's one camera at ``focal`` (a prior the mapper holds), or without a prior."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        camera = db.read_all_cameras()[0]
        if focal is not None:
            camera.params = [focal, focal, 0.5 * size[0], 0.5 * size[1]]
        camera.has_prior_focal_length = focal is not None
        db.update_camera(camera)
    finally:
        db.close()


def _trial(database: Path, image_dir: Path, names: list[str], work_dir: Path,
           size: tuple[int, int], focal: float, min_registered: float, seed: int,
           tag: str = "") -> FocalTrial:
    """Map ``names`` with the focal held at ``focal``."""
    import pycolmap

    start = time.perf_counter()
    copy = work_dir / f"trial{tag}-{focal:.3f}.db"
    shutil.copy(database, copy)
    _set_camera(copy, focal, size)
    _, _, _, mapping = mapping_options(True, seed)
    mapping.image_names = list(names)
    out = work_dir / f"sparse{tag}-{focal:.3f}"
    models = pycolmap.incremental_mapping(copy, image_dir, out, mapping)
    copy.unlink(missing_ok=True)
    shutil.rmtree(out, ignore_errors=True)
    model = max(models.values(), key=lambda m: m.num_reg_images()) if models else None
    registered = model.num_reg_images() if model is not None else 0
    error = (float(model.compute_mean_reprojection_error())
             if model is not None and registered >= min_registered * len(names) else math.inf)
    return FocalTrial(focal=float(focal), registered=int(registered), error=error,
                      seconds=time.perf_counter() - start,
                      points=int(model.num_points3D()) if model is not None else 0)


def _search(database: Path, image_dir: Path, names: list[str], work_dir: Path,
            size: tuple[int, int], coarse: int, refine: tuple[float, ...], min_registered: float,
            seed: int) -> tuple[list[FocalTrial], list[FocalTrial]]:
    """Trials over the coarse grid, then at ``best * r`` and ``best / r`` for each ratio, within
    the grid; all of them in focal order, and the coarse ones."""
    low, high = searched_range(size[0])
    grid = [_trial(database, image_dir, names, work_dir, size, float(f), min_registered, seed)
            for f in np.geomspace(low, high, coarse)]
    grid = _plausible(grid)
    if all(math.isinf(t.error) for t in grid):
        raise SfmError(f"no focal length from {low:.0f} to {high:.0f} px (fields of view "
                       f"{FOV_RANGE_DEG[1]:g} to {FOV_RANGE_DEG[0]:g} deg) registered "
                       f"{min_registered:.0%} of {len(names)} frames")
    trials = list(grid)
    points = float(np.median([t.points for t in grid if t.points]))
    for ratio in refine:
        best = min(trials, key=lambda t: t.error)
        for f in (best.focal / ratio, best.focal * ratio):
            if low <= f <= high and not any(abs(math.log(t.focal / f)) < 0.01 for t in trials):
                trials.append(_plausible([_trial(database, image_dir, names, work_dir, size, f,
                                                 min_registered, seed)], points)[0])
    return sorted(trials, key=lambda t: t.focal), grid


def _plausible(trials: list[FocalTrial], points: float | None = None,
               min_points: float = 0.7) -> list[FocalTrial]:
    """The trials with those that triangulated under ``min_points`` of the median trial's
    points (or of ``points``) marked failed: a model that dropped a third of the scene has the
    error of an easier part of it, not of the focal."""
    typical = points if points is not None else float(np.median([t.points for t in trials]))
    return [t if t.points >= min_points * typical else
            FocalTrial(t.focal, t.registered, math.inf, t.seconds, t.points) for t in trials]


def _one_basin(grid: list[FocalTrial]) -> bool:
    """Whether the coarse trials' errors fall to their minimum and rise after it, the minimum
    inside the grid (at an end the focal may lie beyond the range searched, or nowhere)."""
    errors = [t.error for t in grid]
    k = int(np.argmin(errors))
    if k in (0, len(errors) - 1):
        return False
    falling = all(a >= b for a, b in zip(errors[:k], errors[1:k + 1]))
    rising = all(a <= b for a, b in zip(errors[k:], errors[k + 1:]))
    return falling and rising


def _vertex(trials: list[FocalTrial], reach: float = 1.25) -> tuple[float, float]:
    """The focal at the minimum of a parabola in ``log f`` through the trials within ``reach``
    (a ratio) of the best one, and the vertex's relative standard error from their scatter about
    it; the best trial itself (and no figure) where fewer than three are near or the parabola
    opens downwards."""
    best = min(trials, key=lambda t: t.error)
    near = [t for t in trials if math.isfinite(t.error) and abs(math.log(t.focal / best.focal)) <= math.log(reach)]
    if len(near) < 3:
        return best.focal, 0.0
    x = np.array([math.log(t.focal / best.focal) for t in near])
    e = np.array([t.error for t in near])
    A = np.stack([x ** 2, x, np.ones_like(x)], axis=1)
    coef, *_ = np.linalg.lstsq(A, e, rcond=None)
    a, b, _ = coef
    if a <= 0:
        return best.focal, 0.0
    x0 = float(np.clip(-b / (2 * a), x.min(), x.max()))
    dof = len(near) - 3
    if dof <= 0:
        return best.focal * math.exp(x0), 0.0
    sigma2 = float(np.sum((A @ coef - e) ** 2)) / dof
    cov = sigma2 * np.linalg.inv(A.T @ A)
    grad = np.array([b / (2 * a * a), -1 / (2 * a), 0.0])   # d x0 / d (a, b, c)
    return best.focal * math.exp(x0), float(math.sqrt(max(grad @ cov @ grad, 0.0)))


def _half_vertex(database: Path, image_dir: Path, names: list[str], work_dir: Path,
                 size: tuple[int, int], part: int, focal: float, min_registered: float,
                 seed: int, ratios: tuple[float, ...] = (1.2, 1.0, 1 / 1.2)) -> float | None:
    """The vertex of the first (``part`` 0) or the second half of the frames alone, from trials
    at ``focal`` times ``ratios``; None where a half has too few frames or no parabola."""
    half = len(names) // 2
    part_names = names[:half + 1] if part == 0 else names[half:]
    if len(part_names) < 8:
        return None
    trials = [_trial(database, image_dir, part_names, work_dir, size, focal * r, min_registered,
                     seed, tag=f"h{part}") for r in ratios]
    finite = [t for t in trials if math.isfinite(t.error)]
    if len(finite) < 3:
        return None
    x = np.array([math.log(t.focal / focal) for t in finite])
    a, b, _ = np.polyfit(x, [t.error for t in finite], 2)
    if a <= 0:
        return None
    return focal * math.exp(float(np.clip(-b / (2 * a), 2 * x.min(), 2 * x.max())))


def _rise(trials: list[FocalTrial], best: FocalTrial, ratio: float) -> float:
    """How much the error rises (relative) at the trials about one coarse step (``ratio``) from
    the best, the smaller side (interpolated in ``log f``); inf where a side failed outright."""
    x = np.array([math.log(t.focal / best.focal) for t in trials])
    e = np.array([t.error for t in trials])
    rises = []
    for side in (-1.0, 1.0):
        target = side * math.log(ratio)
        if not (x.min() <= target <= x.max()):
            continue   # the best is at the grid's end: that side is not measured
        finite = np.isfinite(e)
        value = float(np.interp(target, x[finite], e[finite])) if finite.sum() >= 2 else math.inf
        rises.append(value / best.error - 1)
    return float(min(rises)) if rises else 0.0
