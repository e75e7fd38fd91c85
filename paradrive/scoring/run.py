"""Scoring an inference set's generated videos (``paradrive eval --build B --videos V``): one
video at a time (never a whole set in memory), every metric's per-video result or features
cached on disk, and the results gathered per row, per lateral offset and per dataset.

Metrics (``METRICS``): ``psnr`` (PSNR and SSIM against the true novel view, rows with a target
only), ``camera`` (RErr / TErr, :mod:`paradrive.scoring.camera`), ``tce``
(:mod:`paradrive.scoring.flow`), and the feature metrics of :mod:`paradrive.scoring.features`
(``fid``, ``fvd``, ``clip_v``, ``iq``), whose networks load from local weights only.

The cache (``<out>/scores-cache/``) holds one ``.npz`` per (video, metric): the video's SHA-256,
the metric, its settings and, for a network, its weights' SHA-256 make the key, so a re-run reads
what it has and an added metric computes only itself; a file is written under a temporary name
and renamed. FID and FVD are computed per group from the cached features, read back group by
group.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from paradrive.errors import ConfigError, ParaDriveError
from paradrive.scoring.camera import CameraSettings, SourceModel, Located
from paradrive.scoring.features import FEATURE_METRICS, Weights
from paradrive.scoring.flow import Flow, FlowSettings

__all__ = ["METRICS", "WEIGHT_FREE", "ScoreSettings", "VideoScore", "FeatureCache",
           "score_videos", "row_score", "aggregate", "VALUE_NAMES"]

WEIGHT_FREE: tuple[str, ...] = ("psnr", "camera", "tce")
METRICS: tuple[str, ...] = WEIGHT_FREE + FEATURE_METRICS
# the per-video values a metric gives (the CSV's columns, in order)
VALUE_NAMES: dict[str, tuple[str, ...]] = {
    "psnr": ("psnr", "ssim"),
    "camera": ("rerr_deg", "terr", "terr_m", "rerr_m_deg", "located", "sampled"),
    "tce": ("tce",),
    "fid": (), "fvd": (),   # of a group of videos, not of one
    "clip_v": ("clip_v",),
    "iq": ("iq",),
}
ROW_COLUMNS = ["pair_id", "dataset", "scene_id", "camera", "clip", "offset_m", "num_frames",
               "width", "height", "intrinsics", "target_c2w", "rel_pose", "source_uri",
               "source_sha256", "target_uri", "target_sha256"]
CACHE_VERSION = 1   # part of every key: raised when a metric computes its result another way


@dataclass(frozen=True)
class ScoreSettings:
    """What to measure and how: the metrics, the camera and flow protocols, the networks'
    checked weights, their device and the cache folder (None: ``<out>/scores-cache``)."""

    metrics: tuple[str, ...] = WEIGHT_FREE
    camera: CameraSettings = CameraSettings()
    flow: FlowSettings = FlowSettings()
    weights: tuple[Weights, ...] = ()
    device: str = "auto"
    cache: Path | None = None

    def __post_init__(self) -> None:
        unknown = [m for m in self.metrics if m not in METRICS]
        if unknown:
            raise ConfigError(f"--metrics: unknown metric {unknown[0]!r}; the metrics are "
                              f"{', '.join(METRICS)}")
        given = {w.metric for w in self.weights}
        lacking = [m for m in self.metrics if m in FEATURE_METRICS and m not in given]
        if lacking:
            from paradrive.scoring.features import check_weights

            check_weights(lacking[0], None)   # raises, naming the option and the weights


@dataclass
class VideoScore:
    """One row's generated video and what it scored: ``values`` by :data:`VALUE_NAMES` (None
    where not measured), ``error`` when the video could not be scored, ``features`` the cache
    keys of its FID / FVD features and its source's (read back per group)."""

    pair_id: str
    dataset: str
    scene_id: str
    camera: str
    clip: str
    offset_m: float
    video: str
    values: dict[str, float | int | None] = field(default_factory=dict)
    error: str | None = None
    features: dict[str, tuple[str, str]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)   # metric -> why it has no value here

    def record(self) -> dict:
        return {"pair_id": self.pair_id, "dataset": self.dataset, "scene_id": self.scene_id,
                "camera": self.camera, "clip": self.clip, "offset_m": self.offset_m,
                "video": self.video, **self.values, "error": self.error, "skipped": dict(self.skipped)}


class FeatureCache:
    """Per-video results and features as ``<folder>/<key[:2]>/<key>.npz``; counts hits and
    misses."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(**parts: object) -> str:
        text = json.dumps({"cache": CACHE_VERSION, **parts}, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()

    def path(self, key: str) -> Path:
        return self.folder / key[:2] / f"{key}.npz"

    def read(self, key: str) -> dict[str, np.ndarray] | None:
        path = self.path(key)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError):   # a damaged entry is computed again
            return None

    def get(self, key: str, compute: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """The arrays stored under ``key``, else ``compute()``'s, stored."""
        found = self.read(key)
        if found is not None:
            self.hits += 1
            return found
        self.misses += 1
        arrays = compute()
        from paradrive.io import atomic_path

        path = self.path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)  # type: ignore[arg-type]
        return arrays


class _RowVideos:
    """The videos of one row, decoded once each and only when a metric needs them."""

    def __init__(self, build_dir: Path, index, row: dict, video: Path):
        self.build_dir, self.index, self.row, self.video = build_dir, index, row, video

    def _build_video(self, role: str) -> np.ndarray:
        from paradrive.pairs import build_file
        from paradrive.video import decode_frames

        return decode_frames(build_file(self.build_dir, self.row[f"{role}_uri"], role, self.index))

    @functools.cached_property
    def generated(self) -> np.ndarray:
        """uint8 (T, h, w, 3) as generated; its frame count must be the clip's."""
        from paradrive.video import decode_frames

        frames = decode_frames(self.video)
        if len(frames) != self.row["num_frames"]:
            raise ParaDriveError(f"{self.video}: {len(frames)} frames, the row's clip has "
                                 f"{self.row['num_frames']}; generate the build's frame count")
        return frames

    @functools.cached_property
    def generated_at_row_size(self) -> np.ndarray:
        from paradrive.inference import resized

        return resized(self.generated, self.row["width"], self.row["height"])

    @functools.cached_property
    def source(self) -> np.ndarray:
        return self._build_video("source")

    @functools.cached_property
    def target(self) -> np.ndarray:
        return self._build_video("target")


class _Scorer:
    """Everything shared across rows: the settings, the cache, the networks (loaded on their
    first cache miss) and the seconds each metric took."""

    def __init__(self, settings: ScoreSettings, cache: FeatureCache):
        self.settings, self.cache = settings, cache
        self.weights = {w.metric: w for w in settings.weights}
        self._extractors: dict[str, object] = {}
        self._flow: Flow | None = None
        self._sha: dict[str, str] = {}
        self.seconds: dict[str, float] = {m: 0.0 for m in settings.metrics}
        self.computed: dict[str, int] = {m: 0 for m in settings.metrics}

    def weights_sha(self, metric: str) -> str:
        if metric not in self._sha:
            from paradrive.scoring.features import weights_sha256

            self._sha[metric] = weights_sha256(self.weights[metric])
        return self._sha[metric]

    def extractor(self, metric: str):
        if metric not in self._extractors:
            from paradrive.scoring.features import load_extractor

            self._extractors[metric] = load_extractor(self.weights[metric],
                                                      device=self.settings.device)
        return self._extractors[metric]

    def flow(self) -> Flow:
        """TCE's flow (RAFT's network is loaded once, on the first cache miss)."""
        if self._flow is None:
            from paradrive.scoring.raft import flow_of

            self._flow = flow_of(self.settings.flow, self.settings.device)
        return self._flow

    def features_key(self, metric: str, sha: str) -> str:
        return self.cache.key(video=sha, metric=metric, weights=self.weights_sha(metric))

    def features(self, metric: str, sha: str, frames: Callable[[], np.ndarray]) -> np.ndarray:
        """A video's features for ``metric`` (by its SHA-256), from the cache or its network."""
        return self.cache.get(self.features_key(metric, sha), lambda: {
            "features": np.asarray(self.extractor(metric).features(frames()), dtype=np.float64)})[
            "features"]


def _intrinsics(row: dict) -> np.ndarray:
    fx, fy, cx, cy = row["intrinsics"]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _trajectories(row: dict) -> tuple[np.ndarray, np.ndarray]:
    """The row's novel and recorded cameras, (F, 4, 4) c2w each: ``target_c2w`` is the novel
    one, and rel_pose = inv(novel) · recorded."""
    n = row["num_frames"]
    novel = np.asarray(row["target_c2w"], dtype=np.float64).reshape(n, 4, 4)
    rel = np.asarray(row["rel_pose"], dtype=np.float64).reshape(n, 4, 4)
    return novel, novel @ rel


def _camera(sc: _Scorer, row: dict, gen_sha: str, videos: _RowVideos, score: VideoScore) -> dict:
    """RErr / TErr of the video's located frames; the source's model is cached per source."""
    from paradrive.scoring import camera

    s = sc.settings.camera
    frames = camera.sampled_frames(row["num_frames"], s.stride)
    novel, recorded = _trajectories(row)
    K = _intrinsics(row)
    source_key = sc.cache.key(video=row["source_sha256"], metric="camera-source",
                              settings=s.key(), K=K.tolist(),
                              poses=hashlib.sha256(recorded[frames].tobytes()).hexdigest())

    def located() -> dict[str, np.ndarray]:
        model = SourceModel.from_arrays(sc.cache.get(source_key, lambda: camera.triangulate_source(
            videos.source[frames], recorded[frames], K, s).arrays()))
        found = camera.locate(model, videos.generated_at_row_size[frames], K, s)
        return {"c2w": found.c2w, "inliers": found.inliers}

    arrays = sc.cache.get(sc.cache.key(video=gen_sha, source=source_key, metric="camera"), located)
    errors = camera.camera_errors(Located(c2w=arrays["c2w"], inliers=arrays["inliers"]),
                                  novel[frames])
    return {k: getattr(errors, k) for k in VALUE_NAMES["camera"]}


def _psnr(sc: _Scorer, row: dict, gen_sha: str, videos: _RowVideos, score: VideoScore) -> dict:
    """PSNR and SSIM against the row's true view, resized to the generated video's size."""
    from paradrive.inference import resized
    from paradrive.metrics import frames_quality

    def quality() -> dict[str, np.ndarray]:
        pred = videos.generated
        value, structure = frames_quality(pred, resized(videos.target, pred.shape[2], pred.shape[1]))
        return {"psnr": np.asarray(value), "ssim": np.asarray(structure)}

    got = sc.cache.get(sc.cache.key(video=gen_sha, target=row["target_sha256"], metric="psnr"),
                       quality)
    return {k: float(got[k]) for k in ("psnr", "ssim")}


def _tce(sc: _Scorer, row: dict, gen_sha: str, videos: _RowVideos, score: VideoScore) -> dict:
    from paradrive.scoring.flow import tce

    got = sc.cache.get(sc.cache.key(video=gen_sha, metric="tce", settings=sc.settings.flow.key()),
                       lambda: {"pairs": tce(videos.generated, sc.settings.flow, sc.flow())})
    return {"tce": float(np.mean(got["pairs"]))}


def _network(metric: str) -> Callable[[_Scorer, dict, str, _RowVideos, VideoScore], dict]:
    """A feature metric's per-video value: CLIP-V and IQ of the video; FID and FVD only store
    the video's and its source's features, their cache keys kept in ``score.features``."""
    from paradrive.scoring import features as F

    def value(sc: _Scorer, row: dict, gen_sha: str, videos: _RowVideos, score: VideoScore) -> dict:
        gen = sc.features(metric, gen_sha, lambda: videos.generated)
        if metric == "iq":
            return {"iq": F.iq(gen)}
        source = sc.features(metric, row["source_sha256"], lambda: videos.source)
        if metric == "clip_v":
            return {"clip_v": F.clip_v(source, gen)}
        score.features[metric] = (sc.features_key(metric, gen_sha),
                                  sc.features_key(metric, row["source_sha256"]))
        return {}

    return value


# each metric's per-video values: (scorer, row, the video's SHA-256, its videos, its record)
PER_VIDEO = {"psnr": _psnr, "camera": _camera, "tce": _tce,
             **{m: _network(m) for m in FEATURE_METRICS}}


def row_score(sc: _Scorer, build_dir: Path, index, row: dict, video: Path) -> VideoScore:
    """Every asked metric of one row's generated video; a video that cannot be read is the
    row's ``error``, not the run's."""
    from paradrive.io import sha256_file

    score = VideoScore(pair_id=row["pair_id"], dataset=row["dataset"], scene_id=row["scene_id"],
                       camera=row["camera"], clip=row["clip"], offset_m=float(row["offset_m"]),
                       video=str(video))
    videos = _RowVideos(build_dir, index, row, video)
    try:
        gen_sha = sha256_file(video)
        for metric in sc.settings.metrics:
            if metric == "psnr" and row["target_uri"] is None:
                continue
            start, misses = time.perf_counter(), sc.cache.misses
            try:
                score.values.update(PER_VIDEO[metric](sc, row, gen_sha, videos, score))
            except ValueError as exc:   # a video this metric cannot take (too short for FVD, …): the others go on
                score.skipped[metric] = str(exc)
                continue
            if sc.cache.misses > misses:
                sc.seconds[metric] += time.perf_counter() - start
                sc.computed[metric] += 1
    except ParaDriveError as exc:   # a video that cannot be read: the row's error
        score.error = str(exc)
    return score


def _mean(values: Iterable[float | int | None]) -> float | None:
    got = [float(v) for v in values if v is not None]
    return float(np.mean(got)) if got else None


def _group_values(scores: list[VideoScore], metrics: tuple[str, ...], cache: FeatureCache) -> dict:
    """The means of the per-video values of ``scores`` (the videos that gave one), FID and FVD
    of the group (its unique sources against its generated videos)."""
    from paradrive.scoring import features as F

    out: dict[str, float | int | None] = {"videos": len(scores)}
    for metric in metrics:
        for name in VALUE_NAMES[metric]:
            out[name] = _mean(s.values.get(name) for s in scores)
        if metric == "camera":
            out["located_videos"] = sum(1 for s in scores if (s.values.get("located") or 0) > 0)
        if metric in ("fid", "fvd"):
            keys = [s.features[metric] for s in scores if metric in s.features]
            if len(keys) < 2:
                out[metric] = None
                continue
            load = lambda k: cache.get(k, _missing(k))["features"]   # noqa: E731
            gen = [load(g) for g, _ in keys]
            src = [load(k) for k in dict.fromkeys(s for _, s in keys)]
            out[metric] = getattr(F, metric)(src, gen)
    return out


def _missing(key: str) -> Callable[[], dict[str, np.ndarray]]:
    def fail() -> dict[str, np.ndarray]:
        raise ParaDriveError(f"scores cache: features {key} went missing while scoring; run again")
    return fail


def aggregate(scores: list[VideoScore], metrics: tuple[str, ...], cache: FeatureCache) -> dict:
    """The scored videos gathered per (dataset, |offset|) — the paper's ±d columns — with each
    dataset's ``mean`` over its offsets, and per signed offset over every dataset."""
    ok = [s for s in scores if s.error is None]
    table: dict[str, dict[str, dict]] = {}
    for dataset in sorted({s.dataset for s in ok}):
        mine = [s for s in ok if s.dataset == dataset]
        cols = {f"±{d:g}": _group_values([s for s in mine if abs(s.offset_m) == d], metrics, cache)
                for d in sorted({abs(s.offset_m) for s in mine})}
        # a metric some offset lacks has no mean: an average of the others is not the paper's
        mean = {k: None if any(c.get(k) is None for c in cols.values())
                else _mean(c[k] for c in cols.values()) for k in next(iter(cols.values()))}
        mean["videos"] = len(mine)
        table[dataset] = {**cols, "mean": mean}
    by_offset = [{"offset_m": d, **_group_values([s for s in ok if s.offset_m == d], metrics, cache)}
                 for d in sorted({s.offset_m for s in ok})]
    return {"table": table, "by_offset": by_offset}


def score_videos(build_dir: str | Path, videos_dir: str | Path,
                 settings: ScoreSettings | None = None, out_dir: str | Path | None = None) -> dict:
    """Every asked metric of each generated video (``<videos_dir>/<pair_id>.mp4``, one per row
    of the inference set ``build_dir``), gathered per offset and dataset. Streams one row at a
    time; the cache is ``settings.cache`` or ``<out_dir or videos_dir>/scores-cache``."""
    from paradrive.inference import generated_video
    from paradrive.pairs import read_index, read_pairs

    settings = settings or ScoreSettings()
    build_dir, videos_dir = Path(build_dir), Path(videos_dir)
    index = read_index(build_dir)
    if index.kind != "inference":
        raise ParaDriveError(f"{build_dir}: a {index.kind} build; scoring "
                             f"needs an inference set (paradrive build --kind inference)")
    cache = FeatureCache(settings.cache or Path(out_dir or videos_dir) / "scores-cache")
    scorer = _Scorer(settings, cache)
    table = read_pairs(build_dir, ROW_COLUMNS, index, verify=True)
    scores, missing, no_target = [], [], 0
    for batch in table.to_batches(max_chunksize=64):
        for row in batch.to_pylist():
            no_target += row["target_uri"] is None
            video = generated_video(videos_dir, row["pair_id"])
            if video is None:
                missing.append(row["pair_id"])
                continue
            scores.append(row_score(scorer, build_dir, index, row, video))
    return {"build": str(build_dir), "videos": str(videos_dir), "metrics": list(settings.metrics),
            "settings": {"camera": settings.camera.key(), "flow": settings.flow.key(),
                         "device": settings.device,
                         "weights": {w.metric: str(w.path) for w in settings.weights}},
            "rows": [s.record() for s in scores], "missing": missing,
            "failed": [{"pair_id": s.pair_id, "error": s.error} for s in scores if s.error],
            "skipped": [{"pair_id": s.pair_id, "metric": m, "reason": why}
                        for s in scores for m, why in s.skipped.items()],
            "rows_without_target": no_target,
            "cache": {"folder": str(cache.folder), "hits": cache.hits, "misses": cache.misses},
            "seconds": {m: {"videos": scorer.computed[m], "total": round(scorer.seconds[m], 3),
                            "per_video": (round(scorer.seconds[m] / scorer.computed[m], 3)
                                          if scorer.computed[m] else None)}
                        for m in settings.metrics},
            **aggregate(scores, settings.metrics, cache)}
