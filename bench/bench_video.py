"""The ``video:`` input on a real dashcam clip and on the synthetic street: SfM seconds a frame at
two sizes and the plan's estimate of them, the metric scale's error and its reported
uncertainty, held-out PSNR, mask coverage, ingest time and memory; prints JSON (``--out``
writes it too).

    .venv/bin/python bench/bench_video.py [--parts ruler,ingest,sizes,synthetic,kitti,heldout,masks,memory]
        [--clip ../shared/realdata/udacity-freeway] [--height-m 1.23] [--busy] [--out FILE]

Parts (all by default; ``memory`` and ``heldout`` take longest):

* ``ruler``: the clip's own ruler, measured on its undistorted frames without SfM (the lane
  lines and dashes, :func:`measure_ruler`): the frame times at which the near ends of the lane
  dashes pass fixed image rows, grouped into runs of regular passages, each run a whole number
  of Caltrans periods (14.63 m); the camera height from the lane width (3.66 m between line
  centres) and from the dashes' motion between two image rows at the passage speed. ``--write-ruler
  PATH`` stores it for the tests (``tests/udacity_freeway_ruler.json``).
* ``ingest``: ``paradrive.stages.ingest.ingest`` of the clip with its calibration and
  ``--height-m`` in a fresh process: seconds, CPU seconds, peak resident MB, SfM seconds a frame,
  the scale's error against the ruler (the scene's path between the passage times over the
  periods' length) and its reported uncertainty.
* ``threads``: the ``ingest`` part twice more, each in a fresh process: the features found on
  one thread (the baseline) and on every CPU (the default); both wall and CPU seconds, their
  ratio, and whether the two scenes' poses are the same bytes.
* ``sizes``: structure from motion alone (:func:`paradrive.ingest.sfm.reconstruct`, the ingest's
  options) on the clip's frames at 640x360 and 1280x720, each in a fresh process, against what
  ``paradrive plan`` estimates for them; the baseline of the speed figure is SfM at the video's
  own size, in the same run.
* ``synthetic``: the demo street's front camera (130 frames at 320x192, ``paradrive export
  video``) ingested: scale error against the street's truth and the reported uncertainty.
* ``kitti``: the KITTI snippet's frames (``../shared/realdata/kitti-odometry-snippet``) ingested
  without and with their intrinsics: the focal found, the path's length and its trajectory error
  after a rigid and a similarity alignment against the GPS/INS poses, the stated uncertainty and
  the error's ratio to it.
* ``kitti_heldout``: the KITTI snippet fitted twice at the demo profile with every 8th frame held
  out (``fit.holdout_every=8``; ``fit.downscale=4``, 310x94, where the demo fits its 320x192
  street at 2; clips of 49 frames, as 51 frames allow): once on the poses SfM finds from its
  frames (``video:``, without intrinsics), once on the GPS/INS poses written as a one-camera
  DriveStudio folder (Waymo flavour, its rectified intrinsics, no LiDAR;
  :func:`kitti_drivestudio`): the held-out PSNR of each.
* ``heldout``: the clip and the street ingested and fitted with the smoke profile and every 8th
  frame held out (``fit.holdout_every=8``): PSNR on the held-out frames.
* ``masks``: the moving masks against the clip's two cars boxed by hand, and the masks' shares
  and seconds (:func:`mask_coverage`; ``bench_masks.py`` times the masks alone).
* ``memory``: a 130-frame 3840x2160 video made by upscaling the clip 3x (in a temporary folder,
  never kept) ingested: its peak resident MB against the ingest stage's declared ``memory_gb``.

``--busy`` runs a CPU-bound process on every core during the measurements (the machine as a
build shares it). Every process records CPU seconds beside wall seconds (on a shared machine
the CPU seconds are the steadier figure) and its resident peak (``VmHWM``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from spinners import every_core  # noqa: E402  (bench/, the script's own folder)

CLIP = REPO.parent / "shared" / "realdata" / "udacity-freeway"
VIDEO = "freeway-shadows-1280x720.mp4"
# Caltrans lane lines: 12 ft stripes with 36 ft gaps (14.63 m a period); 12 ft (3.66 m) lanes
PERIOD_M = 14.63
LANE_M = 3.66
STREET = "synthetic:demo?seed=7&frames=130&width=320&height=192"
KITTI = REPO.parent / "shared" / "realdata" / "kitti-odometry-snippet"
# the snippet's rectified camera (calib.txt, P0) and KITTI's mount height
KITTI_INTRINSICS = "fx=718.856&fy=718.856&cx=607.1928&cy=185.2157"
KITTI_HEIGHT_M = 1.65
PARTS = ("ruler", "ingest", "threads", "sizes", "synthetic", "kitti", "kitti_heldout", "heldout", "masks",
         "memory")
WITHOUT_CLIP = ("synthetic", "kitti", "kitti_heldout")   # the parts that do not read the freeway clip


# --------------------------------------------------------------------------- the clip's ruler

def undistorted_frames(clip: Path) -> tuple[np.ndarray, dict]:
    """Every frame of the clip undistorted with its calibration (F, H, W, 3), and the calibration."""
    from paradrive.ingest.undistort import undistort_image
    from paradrive.video import decode_frames

    cal = json.loads((clip / "calibration.json").read_text())
    K = np.array([[cal["fx"], 0, cal["cx"] + 0.5], [0, cal["fy"], cal["cy"] + 0.5], [0, 0, 1]])
    dist = [cal[k] for k in ("k1", "k2", "p1", "p2", "k3")]
    frames = decode_frames(clip / VIDEO, seek=False)
    return np.stack([undistort_image(f, K, dist) for f in frames]), cal


def _line(rows: np.ndarray, cols: np.ndarray, slopes: tuple[float, float], rng) -> tuple[float, float, int]:
    """RANSAC line ``col = a + b row`` with ``b`` in ``slopes``: (a, b, inliers)."""
    best = np.zeros(len(rows), dtype=bool)
    for _ in range(400):
        i, j = rng.choice(len(rows), 2, replace=False)
        if rows[i] == rows[j]:
            continue
        b = (cols[j] - cols[i]) / (rows[j] - rows[i])
        if slopes[0] < b < slopes[1]:
            inliers = np.abs(cols - (cols[i] + b * (rows - rows[i]))) < 3
            best = inliers if inliers.sum() > best.sum() else best
    if best.sum() < 30:
        return np.nan, np.nan, 0
    b, a = np.polyfit(rows[best], cols[best], 1)
    return float(a), float(b), int(best.sum())


def lane_lines(frames: np.ndarray, top: int = 500, bottom: int = 680) -> np.ndarray:
    """Per frame: the yellow edge line's and the right dashed line's ``col = a + b row`` fits
    (rows ``top``..``bottom``) and the row where they meet (the vanishing row): (F, 5)."""
    rng = np.random.default_rng(0)
    out = np.full((len(frames), 5), np.nan)
    for f, frame in enumerate(frames):
        img = frame[top:bottom].astype(np.float32)
        grey = img.mean(-1)
        yellow = (img[..., 0] > 120) & (img[..., 1] > 100) & (img[..., 2] < 0.6 * img[..., 1])
        white = (grey - np.median(grey, axis=1, keepdims=True) > 45) & (img.min(-1) > 0.8 * img.max(-1))
        ry, cy = np.nonzero(yellow[:, :750])
        rw, cw = np.nonzero(white[:, 640:1250])
        if len(ry) < 50 or len(rw) < 50:
            continue
        ay, by, _ = _line(ry + top + 0.5, cy + 0.5, (-2.5, -0.8), rng)
        aw, bw, _ = _line(rw + top + 0.5, cw + 640.5, (0.8, 2.5), rng)
        out[f] = (ay, by, aw, bw, (aw - ay) / (by - bw))
    # a fit that locked onto something else (the next lane's line, a car) meets the other line
    # far from where the rest do: such frames take their neighbours' lines
    v0 = np.nanmedian(out[:, 4])
    good = np.isfinite(out[:, 4]) & (np.abs(out[:, 4] - v0) < 12)
    for c in range(5):
        out[~good, c] = np.interp(np.flatnonzero(~good), np.flatnonzero(good), out[good, c])
    return out


def dash_runs(frames: np.ndarray, lines: np.ndarray, top: int = 500, bottom: int = 676) -> list[list[tuple[int, int]]]:
    """Per frame, the runs of rows (first, last) where the right dashed line is painted."""
    rows = np.arange(top, bottom)
    out: list[list[tuple[int, int]]] = []
    for frame, (_, _, a, b, _) in zip(frames, lines):
        if not np.isfinite(b):
            out.append([])
            continue
        grey = frame[top:bottom].astype(np.float32).mean(-1)
        cols = np.round(a + b * (rows + 0.5) - 0.5).astype(int)
        base = np.median(grey[:, 300:1100], axis=1)
        value = np.array([grey[i, max(0, c - 5):c + 6].max() if 0 <= c < grey.shape[1] else 0.0
                          for i, c in enumerate(cols)]) - base
        on = np.flatnonzero(value > 40)
        # painted rows, runs joined across gaps of up to 8 rows (a shadow's edge, worn paint)
        breaks = np.flatnonzero(np.diff(on) > 8)
        runs = [(int(rows[on[a]]), int(rows[on[b]])) for a, b in
                zip(np.r_[0, breaks + 1], np.r_[breaks, len(on) - 1]) if len(on) and on[b] - on[a] >= 2]
        out.append(runs)
    return out


def passages(runs: list[list[tuple[int, int]]], row: float, v0: float, min_rows: int = 15,
             clipped: int = 674) -> np.ndarray:
    """Frame times (fractional) at which a dash's near end passes image row ``row``: between the
    frame where it is above the row and the next, interpolated in inverse depth (the ground
    distance of row ``v`` goes as 1 / (v - v0) on a level road), which holds at any speed."""
    times = []
    for f in range(len(runs) - 1):
        above = [r for r in runs[f] if r[1] - r[0] >= min_rows and r[1] < row]
        below = [r for r in runs[f + 1] if r[1] - r[0] >= min_rows and r[0] < row <= r[1] < clipped]
        if above and below:
            q0, q1, q = 1 / (max(r[1] for r in above) - v0), 1 / (below[0][1] - v0), 1 / (row - v0)
            times.append(f + (q0 - q) / (q0 - q1))
    return np.array(times)


def regular_runs(times: np.ndarray, tolerance: float = 0.08, min_periods: int = 3) -> list[tuple[float, float, int]]:
    """Chains of passages a regular period apart (each gap within ``tolerance`` of the chain's
    mean gap so far, the median gap to start with; the passage nearest a period on taken where
    several are): (first, last, periods) of each chain of at least ``min_periods``. A bridge
    deck whose dashes are spaced otherwise, or a car over the line, breaks a chain; stray
    passages (a shadow's edge across the line) are skipped."""
    median = float(np.median(np.diff(times)))
    out: list[tuple[float, float, int]] = []
    start = 0
    while start < len(times):
        chain = [float(times[start])]
        while True:
            period = (chain[-1] - chain[0]) / (len(chain) - 1) if len(chain) > 1 else median
            near = times[np.abs(times - chain[-1] - period) < tolerance * period]
            if not len(near):
                break
            chain.append(float(near[np.argmin(np.abs(near - chain[-1] - period))]))
        if len(chain) - 1 >= min_periods:
            out.append((chain[0], chain[-1], len(chain) - 1))
        start = int(np.searchsorted(times, chain[-1], side="right")) if len(chain) > 1 else start + 1
    return out


def measure_ruler(clip: Path) -> dict:
    """The clip's ruler (see the module's docstring)."""
    frames, cal = undistorted_frames(clip)
    lines = lane_lines(frames)
    ok = np.isfinite(lines[:, 4]) & (np.abs(lines[:, 4] - np.nanmedian(lines[:, 4])) < 12)
    v0 = float(np.median(lines[ok, 4]))
    runs = dash_runs(frames, lines)
    rows = (560.5, 580.5, 600.5, 620.5)
    segments = [{"row": row, "first": a, "last": b, "periods": n}
                for row in rows for a, b, n in regular_runs(passages(runs, row, v0))]
    # the height by the lane width: the lines' slopes differ by fx W / (fy h)
    slope_gap = lines[ok, 3] - lines[ok, 1]
    by_lane = cal["fx"] / cal["fy"] * LANE_M / slope_gap
    # and by the dashes' motion: between rows r0 and r1 a dash end travels fy h (1/(r0-v0) - 1/(r1-v0))
    r0, r1 = 556.5, 640.5
    first = [s for s in segments if s["row"] == rows[0]][0]
    t0, t1 = passages(runs, r0, v0), passages(runs, r1, v0)
    t0 = t0[(t0 >= first["first"] - 2) & (t0 <= first["last"] + 2)]
    travel = [t1[(t1 > t) & (t1 < t + 6)][0] - t for t in t0 if ((t1 > t) & (t1 < t + 6)).any()]
    speed = PERIOD_M * first["periods"] / (first["last"] - first["first"])   # m a frame
    by_motion = speed * float(np.mean(travel)) / (cal["fy"] * (1 / (r0 - v0) - 1 / (r1 - v0)))
    del frames
    return {"period_m": PERIOD_M, "lane_m": LANE_M, "vanishing_row": v0, "segments": segments,
            "height_by_lane_width_m": float(np.median(by_lane)),
            "height_by_lane_width_iqr_m": [float(q) for q in np.percentile(by_lane, [25, 75])],
            "height_by_dash_motion_m": by_motion,
            "height_by_dash_motion_per_vanishing_px": by_motion * 2 / (r0 + r1 - 2 * v0)}


def scale_error(c2w: np.ndarray, ruler: dict) -> dict:
    """The scene's path between each ruler segment's passages against the periods' length: the
    error of the sum over the segments, and of each."""
    centres = c2w[:, :3, 3]
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))]
    at = lambda t: float(np.interp(t, np.arange(len(along)), along))   # noqa: E731
    per = [(at(s["last"]) - at(s["first"]), s["periods"] * ruler["period_m"]) for s in ruler["segments"]]
    scene, truth = sum(p[0] for p in per), sum(p[1] for p in per)
    return {"error": scene / truth - 1, "segments": [p[0] / p[1] - 1 for p in per],
            "ruler_m": truth, "scene_m": scene}


# --------------------------------------------------------------------------- measured in children

def _child(kind: str, args: dict) -> dict:
    """Run ``kind`` in a fresh interpreter: its figures, seconds, CPU seconds and peak MB."""
    cmd = [sys.executable, __file__, "--child", kind, json.dumps(args)]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if done.returncode:
        return {"error": (done.stdout + done.stderr).strip().splitlines()[-1:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def peak_mb() -> float:
    """This process's resident high-water mark (``VmHWM``): unlike ``ru_maxrss``, which Linux
    carries over an exec, it starts afresh in a new program."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _measured(work) -> dict:
    start, cpu = time.perf_counter(), time.process_time()
    out = work()
    out.update(seconds=time.perf_counter() - start, cpu_s=time.process_time() - cpu, peak_mb=peak_mb())
    return out


def child_ingest(args: dict) -> dict:
    """Ingest ``args['uri']`` into ``args['out']``: the scene's video record and its poses."""
    from paradrive.scene import load_scene
    from paradrive.stages.ingest import ingest, params_of

    if args.get("feature_threads"):
        from paradrive.ingest import sfm

        sfm.feature_threads = lambda: int(args["feature_threads"])

    def work() -> dict:
        params = params_of(args.get("params"))
        summary = ingest(args["uri"], Path(args["out"]), params)
        return {"video": summary["video"], "frames": summary["frames"]}

    out = _measured(work)
    out["c2w"] = load_scene(Path(args["out"])).c2w("front").tolist()
    return out


def child_sfm(args: dict) -> dict:
    """SfM alone on the clip's undistorted frames at ``args['width']`` wide."""
    from paradrive.ingest import sfm
    from paradrive.ingest.video import Calibration, sfm_size
    from paradrive.scene import write_image
    from paradrive.video import each_frame

    cal = json.loads(Path(args["calib"]).read_text())
    calib = Calibration(cal["fx"], cal["fy"], cal["cx"], cal["cy"],
                        tuple(cal[k] for k in ("k1", "k2", "p1", "p2", "k3")), None, "")
    w, h = sfm_size(cal["width"], cal["height"], args["width"])
    K = calib.at(cal["width"], cal["height"])
    K = sfm.Intrinsics(K.fx * w / cal["width"], K.fy * h / cal["height"], K.cx * w / cal["width"],
                       K.cy * h / cal["height"])
    work = Path(args["work"])
    names: list[str] = []

    def keep(i: int, pixels) -> None:
        from paradrive.ingest.undistort import undistort_image

        names.append(f"{i:06d}.png")
        write_image(work / "images" / names[-1], undistort_image(pixels, K.K(), calib.distortion))

    each_frame(args["video"], None, keep, size=(h, w), seek=False)
    out = _measured(lambda: {"registered": int(sfm.reconstruct(work / "images", names, work,
                                                                intrinsics=K).registered.sum())})
    out.update(width=w, height=h, frames=len(names), seconds_a_frame=out["seconds"] / len(names),
               cpu_s_a_frame=out["cpu_s"] / len(names))
    return out


# --------------------------------------------------------------------------- the parts

def clip_uri(clip: Path, height: float) -> str:
    return f"video:{clip / VIDEO}?calib=calibration.json&height_m={height:g}"


def street_video(workdir: Path) -> str:
    """The demo street's front camera as a plain video (``paradrive export video``): its URI."""
    from paradrive.ingest.export import export_scene
    from paradrive.stages.ingest import params_of

    return export_scene(STREET, "video", workdir / "street", params_of())


def part_ingest(clip: Path, height: float, ruler: dict, workdir: Path) -> dict:
    uri = clip_uri(clip, height)
    out = _child("ingest", {"uri": uri, "out": str(workdir / "clip")})
    if "error" in out:
        return out
    c2w = np.array(out.pop("c2w"))
    video = out.pop("video")
    scale = video["scale"]
    return {**out, "uri": uri, "sfm_s_a_frame": video["sfm"]["seconds"] / video["sampled"],
            "sfm_size": [video["sfm"]["width"], video["sfm"]["height"]],
            "registered": video["registered"], "uncertainty": scale["uncertainty"],
            "road_motion": scale.get("road_motion"), "scale_vs_ruler": scale_error(c2w, ruler)}


def part_threads(clip: Path, height: float, workdir: Path) -> dict:
    """The clip's ingest with the features on one thread, then on every CPU."""
    uri = clip_uri(clip, height)
    runs = {name: _child("ingest", {"uri": uri, "out": str(workdir / f"threads-{name}"),
                                     "feature_threads": threads})
            for name, threads in (("one", 1), ("all", None))}
    if any("error" in r for r in runs.values()):
        return runs
    same = runs["one"].pop("c2w") == runs["all"].pop("c2w")
    figures = {name: {"seconds": r["seconds"], "cpu_s": r["cpu_s"], "peak_mb": r["peak_mb"],
                      "sfm_seconds": r["video"]["sfm"]["seconds"]} for name, r in runs.items()}
    return {**figures, "same_poses": same, "speedup": figures["one"]["seconds"] / figures["all"]["seconds"],
            "sfm_speedup": figures["one"]["sfm_seconds"] / figures["all"]["sfm_seconds"]}


def part_sizes(clip: Path, workdir: Path) -> dict:
    from paradrive.pipeline import StageRegistry
    from paradrive.pipeline.budget import plan_build

    out = {}
    for width in (1280, 640):
        measured = _child("sfm", {"calib": str(clip / "calibration.json"), "video": str(clip / VIDEO),
                                  "width": width, "work": str(workdir / f"sfm{width}")})
        config = StageRegistry().resolve(None, {"ingest": {"video_sfm_width": width}})
        plan = plan_build(config, [f"video:{clip / VIDEO}?calib=calibration.json"], None)
        measured["plan_s"] = plan.seconds["sfm"]
        if "seconds" in measured:
            measured["plan_vs_measured"] = plan.seconds["sfm"] / measured["seconds"]
            measured["plan_vs_cpu"] = plan.seconds["sfm"] / measured["cpu_s"]
        out[f"{width}"] = measured
    if "seconds" in out["1280"] and "seconds" in out["640"]:
        out["speedup_640_vs_1280"] = out["1280"]["seconds"] / out["640"]["seconds"]
        out["exponent"] = float(np.log(out["1280"]["cpu_s"] / out["640"]["cpu_s"]) / np.log(4))
    return out


def part_synthetic(workdir: Path) -> dict:
    from paradrive.ingest.sfm import path_length
    from paradrive.synthetic import SyntheticStreet

    uri = street_video(workdir)
    out = _child("ingest", {"uri": uri, "out": str(workdir / "street-scene")})
    if "error" in out:
        return out
    c2w = np.array(out.pop("c2w"))
    truth = SyntheticStreet(name="demo", seed=7, frames=130, width=320, height=192).c2w("front")
    video = out.pop("video")
    first, last = video["kept"]   # the steady run SfM placed: its own stretch of the truth
    error = path_length(c2w) / path_length(truth[first:last + 1]) - 1
    return {**out, "uri": uri, "kept": video["kept"], "scale_error": error,
            "uncertainty": video["scale"]["uncertainty"],
            "ratio": abs(error) / video["scale"]["uncertainty"],
            "sfm_s_a_frame": video["sfm"]["seconds"] / video["sampled"]}


def rigid_error(found: np.ndarray, truth: np.ndarray, *, scale: bool = False) -> float:
    """RMS distance (units of ``truth``) between the centres ``found`` and ``truth`` (N, 3)
    after the rigid motion (with ``scale``: the similarity) that fits them best (Kabsch)."""
    a, b = found - found.mean(0), truth - truth.mean(0)
    u, sv, vt = np.linalg.svd(a.T @ b)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rotation = vt.T @ d @ u.T
    s = float((sv * np.diag(d)).sum() / (a ** 2).sum()) if scale else 1.0
    return float(np.sqrt(((s * a @ rotation.T - b) ** 2).sum(1).mean()))


def part_kitti(folder: Path, workdir: Path) -> dict:
    """The KITTI snippet's frames ingested without and with their intrinsics: focal, frames
    registered, path length and trajectory error against the GPS/INS poses, stated uncertainty."""
    truth = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    out = {}
    for name, query in (("no_intrinsics", f"height_m={KITTI_HEIGHT_M}"),
                        ("intrinsics", f"{KITTI_INTRINSICS}&height_m={KITTI_HEIGHT_M}")):
        uri = f"video:{folder / 'image_l'}?{query}"
        got = _child("ingest", {"uri": uri, "out": str(workdir / f"kitti-{name}")})
        if "error" in got:
            out[name] = got
            continue
        centres = np.array(got.pop("c2w"))[:, :3, 3]
        video = got.pop("video")
        first, last = video["kept"]
        true = truth[first:last + 1]
        length = float(np.linalg.norm(np.diff(true, axis=0), axis=1).sum())
        error = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()) / length - 1
        scale = video["scale"]
        out[name] = {**got, "uri": uri, "registered": video["registered"],
                     "fx": video["intrinsics"]["fx"], "path_error": error,
                     "uncertainty": scale["uncertainty"], "ratio": abs(error) / scale["uncertainty"],
                     "parts": scale["parts"], "weights": scale["weights"],
                     "ate_rigid_of_path": rigid_error(centres, true) / length,
                     "ate_similarity_of_path": rigid_error(centres, true, scale=True) / length,
                     "focal_seconds": video["sfm"].get("focal_seconds")}
    return out


def kitti_drivestudio(folder: Path, out: Path) -> str:
    """The KITTI snippet on its GPS/INS poses as a one-camera DriveStudio folder (Waymo
    flavour: camera 0, its rectified intrinsics from ``calib.txt``, the camera
    ``KITTI_HEIGHT_M`` above the vehicle's origin, no LiDAR, no sky masks): its URI."""
    from PIL import Image

    from paradrive import geometry
    from paradrive.ingest.common import OPENCV_TO_FLU

    first = (folder / "calib.txt").read_text().split("\n", 1)[0].removeprefix("P0:")  # P0, then P1
    P0 = np.array(first.split(), dtype=np.float64).reshape(3, 4)
    for sub in ("images", "ego_pose", "extrinsics", "intrinsics"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    mount = np.eye(4)
    mount[2, 3] = KITTI_HEIGHT_M                      # camera (x forward, y left, z up) -> vehicle
    np.savetxt(out / "extrinsics" / "0.txt", mount)
    np.savetxt(out / "intrinsics" / "0.txt", [P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2], 0, 0, 0, 0, 0])
    # the reader's camera pose is ego @ mount @ OPENCV_TO_FLU: the vehicle pose that gives KITTI's
    back = geometry.invert(OPENCV_TO_FLU) @ geometry.invert(mount)
    for t, pose in enumerate(np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)):
        np.savetxt(out / "ego_pose" / f"{t:03d}.txt", geometry.make_pose(pose[:, :3], pose[:, 3]) @ back)
        Image.open(folder / "image_l" / f"{t:06d}.png").convert("RGB").save(
            out / "images" / f"{t:03d}_0.jpg", quality=95)
    return f"drivestudio:{out}"


def part_kitti_heldout(folder: Path, workdir: Path) -> dict:
    """The KITTI snippet fitted on the poses from its frames and on its GPS/INS poses."""
    uris = {"sfm_poses": f"video:{folder / 'image_l'}?height_m={KITTI_HEIGHT_M}",
            "gps_ins_poses": kitti_drivestudio(folder, workdir / "kitti-drivestudio")}
    # 51 frames: clips of 49 (4k + 1), which the build checks before it fits
    return part_heldout(uris, workdir, profile="demo",
                        overrides={"fit": {"downscale": 4}, "render": {"clip_frames": 49}})


def part_heldout(uris: dict[str, str], workdir: Path, *, profile: str = "smoke",
                 overrides: dict | None = None) -> dict:
    """Ingest and fit each scene with ``profile`` (``overrides`` over it, per stage) and every
    8th frame held out."""
    from paradrive.contracts.layout import SceneLayout
    from paradrive.contracts.records import FitRecord
    from paradrive.pipeline import StageRegistry, run_build
    from paradrive.uri import parse_uri

    stages = {stage: dict(values) for stage, values in (overrides or {}).items()}
    stages.setdefault("fit", {})["holdout_every"] = 8
    config = StageRegistry().resolve(profile, stages)
    out = {}
    for name, uri in uris.items():
        start = time.perf_counter()
        report = run_build(config, [uri], workdir / "heldout", stages=["ingest", "fit"],
                           manifests_dir=workdir / "manifests")
        failures = [r.error for r in report.failures()]
        layout = SceneLayout.of(workdir / "heldout", parse_uri(uri).scene_id)
        if failures or not layout.fit_json.is_file():
            out[name] = {"error": failures}
            continue
        record = FitRecord.load(layout.fit_json)
        out[name] = {"uri": uri, "heldout_psnr": record.heldout.psnr if record.heldout else None,
                     "seconds": time.perf_counter() - start}
    return out


def mask_coverage(scene_dir: Path, clip: Path) -> dict | None:
    """The clip's moving masks against its two cars boxed by hand on eleven frames
    (tests/udacity_freeway_cars.json): the share of the box pixels masked, pooled and per car,
    and of the static road; with what ``scene.json`` records of the masks (the ego mask's and the
    moving masks' shares, their seconds). None where the scene has no masks."""
    if not (scene_dir / "masks" / "motion").is_dir():
        return None
    from paradrive.ingest.videomasks import labelled_scores

    s = labelled_scores(scene_dir, REPO / "tests" / "udacity_freeway_cars.json", clip / "calibration.json")
    recorded = json.loads((scene_dir / "scene.json").read_text())["video"].get("masks", {})
    return {"coverage": s.coverage, "named": s.named, "worst_frame_coverage": s.worst_coverage,
            "road_masked": s.road_masked, "worst_frame_road_masked": s.worst_road_masked, **recorded}


def part_memory(clip: Path, workdir: Path) -> dict:
    """A 130-frame 4K video (the clip upscaled 3x), ingested under the ingest's declared memory."""
    from PIL import Image

    from paradrive.pipeline import StageRegistry
    from paradrive.video import decode_frames, encode_video

    path = workdir / "uhd.mp4"
    frames = decode_frames(clip / VIDEO, list(range(130)), seek=False)
    encode_video(path, (np.asarray(Image.fromarray(f).resize((3840, 2160), Image.Resampling.BICUBIC))
                        for f in frames), 25.0, preset="ultrafast")
    shutil.copy(clip / "calibration.json", workdir / "calibration.json")
    declared = StageRegistry().resolve(None).registry().specs["ingest"].resources.memory_gb
    out = _child("ingest", {"uri": f"video:{path}?calib=calibration.json&height_m=1.23",
                            "out": str(workdir / "uhd-scene")})
    out.pop("c2w", None)
    video = out.pop("video", {})
    return {**out, "declared_memory_gb": declared, "within": out.get("peak_mb", 1e9) < declared * 1024,
            "sfm_size": [video.get("sfm", {}).get("width"), video.get("sfm", {}).get("height")],
            "registered": video.get("registered"), "uncertainty": video.get("scale", {}).get("uncertainty")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default=",".join(PARTS))
    parser.add_argument("--clip", type=Path, default=CLIP)
    parser.add_argument("--height-m", type=float, default=1.23,
                        help="the clip's camera height (docs/scene-layout.md: how it was measured)")
    parser.add_argument("--busy", action="store_true", help="a CPU-bound process on every core")
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--write-ruler", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args, rest = parser.parse_known_args()
    if args.child:
        print(json.dumps({"ingest": child_ingest, "sfm": child_sfm}[args.child](json.loads(rest[0]))))
        return
    parts = args.parts.split(",")
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench-video-"))
    result: dict = {"load_average": os.getloadavg(), "cpus": os.cpu_count(), "busy": args.busy,
                    "height_m": args.height_m}
    if not (args.clip / VIDEO).is_file():   # a clone without the real recordings: the street only
        result["clip"] = f"not found: {args.clip / VIDEO}; its parts are skipped"
        parts = [p for p in parts if p in WITHOUT_CLIP]
    with every_core(args.busy):
        ruler = measure_ruler(args.clip) if set(parts) - set(WITHOUT_CLIP) else {}
        result["ruler"] = ruler
        if args.write_ruler and ruler:
            args.write_ruler.write_text(json.dumps(ruler, indent=1) + "\n")
        if "ingest" in parts:
            result["ingest"] = part_ingest(args.clip, args.height_m, ruler, workdir)
            result["masks"] = mask_coverage(workdir / "clip", args.clip)
        if "threads" in parts:
            result["threads"] = part_threads(args.clip, args.height_m, workdir)
        if "sizes" in parts:
            result["sizes"] = part_sizes(args.clip, workdir)
        if "synthetic" in parts:
            result["synthetic"] = part_synthetic(workdir)
        if "kitti" in parts:
            result["kitti"] = (part_kitti(KITTI, workdir) if (KITTI / "image_l").is_dir()
                               else f"not found: {KITTI}")
        if "kitti_heldout" in parts:
            result["kitti_heldout"] = (part_kitti_heldout(KITTI, workdir) if (KITTI / "image_l").is_dir()
                                       else f"not found: {KITTI}")
        if "heldout" in parts:
            result["heldout"] = part_heldout({"clip": clip_uri(args.clip, args.height_m),
                                              "street": street_video(workdir)}, workdir)
        if "memory" in parts:
            result["memory"] = part_memory(args.clip, workdir)
    result["load_average_after"] = os.getloadavg()
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    if args.workdir is None:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
