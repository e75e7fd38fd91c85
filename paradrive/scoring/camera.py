"""Camera accuracy of a generated video (RErr, TErr): where its cameras are, against the novel
trajectory the row asked for. No weights: features, triangulation and pose estimation run on the
CPU.

The paper recovers each generated video's cameras with MegaSaM and scores them as CamCloneMaster
does, after CameraCtrl and CamI2V. Here the cameras come from structure from motion against the
row's own source video, whose poses and intrinsics the inference set knows:

1. :func:`triangulate_source`: SIFT keypoints (OpenCV, at most ``max_features`` a frame) on every
   ``stride``-th frame of the source video (every 4th: the cadence of ReCamMaster's camera
   format, 31 frames of a 121-frame clip), matched between sampled frames 1 and 2 apart (Lowe's
   ratio test), triangulated with the recorded poses held fixed; a point is kept when it lies in
   front of both cameras, reprojects within ``max_reproj_px`` in both and its rays meet at
   ``min_angle_deg`` or more (a forward-moving camera sees little parallax near the centre).
2. :func:`locate`: each sampled generated frame's keypoints are matched with the triangulated
   ones of the source frames up to ``neighbours`` sampled frames either side, and its camera is
   the perspective-n-point solution (RANSAC, ``ransac_px``, then Levenberg-Marquardt on the
   inliers) with the row's intrinsics held fixed. A frame with fewer than ``min_inliers``
   inliers (COLMAP's default for registering an image, 30) is *not located* and gets no number.
   Pixel centres sit at +0.5 (docs/conventions.md); OpenCV's keypoints are shifted to match.

Two forms of the error are reported from the located cameras (:func:`camera_errors`):

* **the paper's relative form** (CamI2V's ``glomap_evaluation``, CameraCtrl's sums): both
  trajectories relative to their first located frame, each one's translations divided by its
  own largest norm; ``rerr_deg`` is the sum over located frames of the angle of R_refᵀ R_est,
  degrees, and ``terr`` the sum of the distances between the normalised translations (no
  unit). It compares motion, not place: a video that stays on the recorded path moves as the
  shifted target does, and scores about the same at ±1 m as at ±4 m. Sums grow with the number
  of located frames, so the count is reported beside them.
* **the shift-visible metric form**: the located cameras are in the source's world, metres, so
  ``terr_m`` is the mean over located frames of the distance between each camera centre and the
  requested novel one, and ``rerr_m_deg`` the mean angle between their rotations. A video that
  stays on the recorded path scores about |offset| here.

What that changes against MegaSaM: a generated frame is only placed when it shares enough
verified features with the source video; a video that does not resemble its source gets no pose
(``located`` 0) where MegaSaM would give it one, and its errors are left out of the means.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from paradrive import geometry

__all__ = ["CameraSettings", "SourceModel", "Located", "CameraErrors", "sampled_frames",
           "triangulate_source", "locate", "relative_errors", "metric_errors", "camera_errors"]


@dataclass(frozen=True)
class CameraSettings:
    """How the cameras of a generated video are found (the defaults are the protocol above;
    tests sample every frame of their short clips)."""

    stride: int = 4
    max_features: int = 4000
    contrast: float = 0.02
    ratio: float = 0.8
    pair_gaps: tuple[int, ...] = (1, 2, 3)
    max_reproj_px: float = 2.0
    min_angle_deg: float = 0.5
    neighbours: int = 2
    ransac_px: float = 4.0
    min_inliers: int = 30

    def key(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


@dataclass
class SourceModel:
    """The triangulated keypoints of a source video, per sampled frame k: pixel positions
    ``xy[k]`` (M_k, 2) float32 (centres at +0.5), SIFT descriptors ``desc[k]`` (M_k, 128) uint8
    and world points ``xyz[k]`` (M_k, 3) float64, metres."""

    xy: list[np.ndarray]
    desc: list[np.ndarray]
    xyz: list[np.ndarray]

    @property
    def points(self) -> int:
        return int(sum(len(p) for p in self.xyz))

    def arrays(self) -> dict[str, np.ndarray]:
        """The model as flat arrays (for an .npz cache file); :meth:`from_arrays` reads them."""
        counts = np.array([len(p) for p in self.xyz], dtype=np.int64)
        return {"counts": counts, "xy": np.concatenate(self.xy).reshape(-1, 2),
                "desc": np.concatenate(self.desc).reshape(-1, 128),
                "xyz": np.concatenate(self.xyz).reshape(-1, 3)}

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray]) -> SourceModel:
        cut = np.cumsum(a["counts"])[:-1]
        return cls(xy=np.split(a["xy"], cut), desc=np.split(a["desc"], cut),
                   xyz=np.split(a["xyz"], cut))


@dataclass(frozen=True)
class Located:
    """Cameras of a generated video's sampled frames: c2w (n, 4, 4) OpenCV camera-to-world in
    the source's world (NaN where not located), inliers (n,) of each frame's pose."""

    c2w: np.ndarray
    inliers: np.ndarray

    @property
    def located(self) -> np.ndarray:
        return np.isfinite(self.c2w[:, 0, 0])


@dataclass(frozen=True)
class CameraErrors:
    """One video's camera errors (None where fewer than two frames, or none, were located)."""

    sampled: int
    located: int
    rerr_deg: float | None
    terr: float | None
    terr_m: float | None
    rerr_m_deg: float | None


def sampled_frames(num_frames: int, stride: int) -> np.ndarray:
    """Clip frame indices scored: 0, stride, 2 stride, … below ``num_frames`` (n,)."""
    return np.arange(0, num_frames, max(1, stride), dtype=np.int64)


def _sift(frame: np.ndarray, settings: CameraSettings) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints of a uint8 (H, W, 3) RGB frame: (M, 2) float32 pixels, centres at +0.5,
    and (M, 128) uint8 descriptors (OpenCV's are whole numbers up to 255)."""
    import cv2

    sift = cv2.SIFT_create(  # type: ignore[attr-defined]
        nfeatures=settings.max_features, contrastThreshold=settings.contrast)
    grey = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    keypoints, desc = sift.detectAndCompute(grey, None)
    if desc is None:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8)
    xy = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2) + 0.5
    return xy, np.clip(np.rint(desc), 0, 255).astype(np.uint8)


def _match(a: np.ndarray, b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of descriptors of ``a`` (Ma, 128) whose nearest neighbour in ``b`` passes
    Lowe's ratio test."""
    import cv2

    if len(a) < 2 or len(b) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.astype(np.float32), b.astype(np.float32), k=2)
    good = np.array([(m.queryIdx, m.trainIdx) for m, n in (p for p in pairs if len(p) == 2)
                     if m.distance < ratio * n.distance], dtype=np.int64).reshape(-1, 2)
    return good[:, 0], good[:, 1]


def _projection(c2w: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The (3, 4) projection matrix K [R | t] of a camera c2w (4, 4)."""
    return K @ geometry.invert(c2w)[:3]


def _epipolar_px(xa: np.ndarray, xb: np.ndarray, ca: np.ndarray, cb: np.ndarray,
                 K: np.ndarray) -> np.ndarray:
    """The Sampson distance, pixels, of matched pixels xa, xb (M, 2) to the epipolar geometry
    of the known cameras ca, cb (4, 4 c2w): (M,)."""
    rel = geometry.invert(cb) @ ca                      # camera a -> camera b
    t = rel[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    Ki = np.linalg.inv(K)
    F = Ki.T @ tx @ rel[:3, :3] @ Ki
    ha = np.column_stack([xa, np.ones(len(xa))])
    hb = np.column_stack([xb, np.ones(len(xb))])
    Fa, Fb = ha @ F.T, hb @ F
    num = np.sum(hb * Fa, axis=1) ** 2
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


def _tracks(feats: list[tuple[np.ndarray, np.ndarray]], c2w: np.ndarray, K: np.ndarray,
            settings: CameraSettings) -> list[list[tuple[int, int]]]:
    """Keypoints chained into tracks by the matches between sampled frames ``pair_gaps``
    apart that agree with the known epipolar geometry (within ``max_reproj_px``): each track a
    list of (frame, keypoint); a track seeing one frame twice is dropped."""
    offsets = np.cumsum([0] + [len(f[0]) for f in feats])
    parent = np.arange(offsets[-1])

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for gap in settings.pair_gaps:
        for a in range(len(feats) - gap):
            b = a + gap
            ia, ib = _match(feats[a][1], feats[b][1], settings.ratio)
            if not len(ia):
                continue
            good = _epipolar_px(feats[a][0][ia], feats[b][0][ib], c2w[a], c2w[b], K) \
                <= settings.max_reproj_px
            for i, j in zip(ia[good] + offsets[a], ib[good] + offsets[b]):
                parent[root(int(i))] = root(int(j))
    groups: dict[int, list[tuple[int, int]]] = {}
    frame_of = np.repeat(np.arange(len(feats)), np.diff(offsets))
    for g in range(offsets[-1]):
        groups.setdefault(root(g), []).append((int(frame_of[g]), int(g - offsets[frame_of[g]])))
    return [t for t in groups.values()
            if len(t) >= 2 and len({f for f, _ in t}) == len(t)]


def _triangulate(track: list[tuple[int, int]], feats: list[tuple[np.ndarray, np.ndarray]],
                 P: np.ndarray, c2w: np.ndarray, settings: CameraSettings) -> np.ndarray | None:
    """The world point (3,) of one track from all its views (linear least squares over the
    projections P (n, 3, 4)), or None when it falls behind a camera, reprojects beyond
    ``max_reproj_px`` in any view or its widest ray angle is under ``min_angle_deg``."""
    rows = []
    for f, k in track:
        u, v = feats[f][0][k]
        rows += [u * P[f][2] - P[f][0], v * P[f][2] - P[f][1]]
    hom = np.linalg.svd(np.array(rows))[2][-1]
    if abs(hom[3]) < 1e-12:
        return None
    X = hom[:3] / hom[3]
    rays = []
    for f, k in track:
        cam = P[f] @ np.append(X, 1.0)
        if cam[2] <= 0 or np.hypot(*(cam[:2] / cam[2] - feats[f][0][k])) > settings.max_reproj_px:
            return None
        rays.append((X - c2w[f][:3, 3]) / np.linalg.norm(X - c2w[f][:3, 3]))
    widest = min(float(np.dot(r, q)) for r in rays for q in rays)
    if np.degrees(np.arccos(np.clip(widest, -1.0, 1.0))) < settings.min_angle_deg:
        return None
    return X


def triangulate_source(frames: np.ndarray, c2w: np.ndarray, K: np.ndarray,
                       settings: CameraSettings) -> SourceModel:
    """The source video's model: frames uint8 (n, H, W, 3) (the sampled ones), their recorded
    cameras c2w (n, 4, 4) and intrinsics K (3, 3). Each track is triangulated from every frame
    that sees it, so its depth rests on the longest baseline of the clip."""
    feats = [_sift(f, settings) for f in frames]
    P = np.stack([_projection(c, K) for c in c2w])
    point: list[dict[int, np.ndarray]] = [{} for _ in frames]
    for track in _tracks(feats, c2w, K, settings):
        X = _triangulate(track, feats, P, c2w, settings)
        if X is not None:
            for f, k in track:
                point[f][k] = X
    xy, desc, xyz = [], [], []
    for (pts, ds), chosen in zip(feats, point):
        idx = np.array(sorted(chosen), dtype=np.int64)
        xy.append(pts[idx].reshape(-1, 2))
        desc.append(ds[idx].reshape(-1, 128))
        xyz.append(np.array([chosen[i] for i in idx], dtype=np.float64).reshape(-1, 3))
    return SourceModel(xy=xy, desc=desc, xyz=xyz)


def _pose(obj: np.ndarray, img: np.ndarray, K: np.ndarray,
          settings: CameraSettings) -> tuple[np.ndarray | None, int]:
    """c2w (4, 4) from world points obj (M, 3) seen at pixels img (M, 2), and its inliers; None
    below ``min_inliers``."""
    import cv2

    if len(obj) < max(settings.min_inliers, 6):
        return None, 0
    cv2.setRNGSeed(0)
    # OpenCV's pixel centres sit at whole numbers, the builder's at +0.5
    img_cv, K_cv = (img - 0.5).astype(np.float64), K - _centre_shift()
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img_cv, K_cv, None, iterationsCount=1000, reprojectionError=settings.ransac_px,
            confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inliers is None or len(inliers) < settings.min_inliers:
            return None, 0 if inliers is None else len(inliers)
        idx = inliers[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img_cv[idx], K_cv, None, rvec, tvec)
    except cv2.error:   # degenerate points (all on one line, …): the frame is not located
        return None, 0
    w2c = np.eye(4)
    w2c[:3, :3] = cv2.Rodrigues(rvec)[0]
    w2c[:3, 3] = tvec[:, 0]
    return geometry.invert(w2c), len(idx)


def _centre_shift() -> np.ndarray:
    """What turns the builder's K (centres at +0.5) into OpenCV's (centres at whole numbers)."""
    shift = np.zeros((3, 3))
    shift[0, 2] = shift[1, 2] = 0.5
    return shift


def locate(model: SourceModel, frames: np.ndarray, K: np.ndarray,
           settings: CameraSettings) -> Located:
    """The cameras of a generated video's sampled frames uint8 (n, H, W, 3) (the same frames as
    the model's, at the row's size) in the source's world."""
    n = len(frames)
    c2w = np.full((n, 4, 4), np.nan)
    inliers = np.zeros(n, dtype=np.int64)
    for i, frame in enumerate(frames):
        xy, desc = _sift(frame, settings)
        taken: dict[int, np.ndarray] = {}
        near = sorted(range(max(0, i - settings.neighbours),
                            min(len(model.xyz), i + settings.neighbours + 1)), key=lambda j: abs(j - i))
        for j in near:
            ia, ib = _match(desc, model.desc[j], settings.ratio)
            for a, b in zip(ia.tolist(), ib.tolist()):
                taken.setdefault(a, model.xyz[j][b])
        if not taken:
            continue
        kp = np.array(sorted(taken), dtype=np.int64)
        pose, count = _pose(np.array([taken[k] for k in kp]), xy[kp].astype(np.float64), K, settings)
        inliers[i] = count
        if pose is not None:
            c2w[i] = pose
    return Located(c2w=c2w, inliers=inliers)


def _angles_deg(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Angle of ra_iᵀ rb_i, degrees, for rotations ra, rb (m, 3, 3)."""
    trace = np.einsum("nji,nji->n", ra, rb)
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def relative_errors(est: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """The paper's (CamI2V's) RErr, degrees, and TErr, no unit, of the cameras est against ref
    (m, 4, 4 c2w, the same frames): relative to the first, translations over their own largest
    norm, summed over the m frames."""
    def normalised(c2w: np.ndarray) -> np.ndarray:
        rel = geometry.invert(c2w[0])[None] @ c2w
        scale = np.linalg.norm(rel[:, :3, 3], axis=1).max() + 1e-9
        out = rel.copy()
        out[:, :3, 3] /= scale
        return out

    e, r = normalised(est), normalised(ref)
    rerr = float(_angles_deg(r[:, :3, :3], e[:, :3, :3]).sum())
    terr = float(np.linalg.norm(e[:, :3, 3] - r[:, :3, 3], axis=1).sum())
    return rerr, terr


def metric_errors(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame camera centre distance, metres, and rotation angle, degrees, between est and
    ref (m, 4, 4 c2w in the same world): (m,), (m,)."""
    return (np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1),
            _angles_deg(ref[:, :3, :3], est[:, :3, :3]))


def camera_errors(located: Located, novel: np.ndarray) -> CameraErrors:
    """Both forms of the error of the located cameras against the requested novel cameras
    novel (n, 4, 4 c2w, the sampled frames); frames not located are left out."""
    ok = located.located
    n, m = len(ok), int(ok.sum())
    if m == 0:
        return CameraErrors(sampled=n, located=0, rerr_deg=None, terr=None, terr_m=None,
                            rerr_m_deg=None)
    est, ref = located.c2w[ok], novel[ok]
    dist, angle = metric_errors(est, ref)
    rerr, terr = relative_errors(est, ref) if m >= 2 else (None, None)
    return CameraErrors(sampled=n, located=m, rerr_deg=rerr, terr=terr,
                        terr_m=float(dist.mean()), rerr_m_deg=float(angle.mean()))
