"""nuScenes v1.0-trainval tables: building their index, one scene's lookup and ingest; prints JSON.

    .venv/bin/python bench/bench_nuscenes_tables.py [--scale 1.0] [--baseline-scale 0.1] [--root DIR]

Generates tables shaped like v1.0-trainval's (850 scenes at ``--scale 1``; per scene about 40
samples, 3.1K sample_data and as many ego_pose rows, 1.4K sample_annotation rows of 76
instances, which gives the real totals: 34K samples, 2.6M sample_data / ego_pose, 1.17M
annotations), with one scene's images and LiDAR sweeps on disk (one JPEG and one sweep linked
under every file name). Each measurement runs in a fresh process, which reports its wall time
and peak memory (``VmHWM``):

- ``build``: the index from scratch (``open_tables`` on a version without one);
- ``lookup``: a scene's rows through the index (open it, walk the sample and sensor chains,
  read every frame's ego pose and calibration, build the actors), for several scenes;
- ``ingest``: the whole ingest of the scene with images (six cameras, LiDAR, dynamic masks);
- ``baseline``: the same lookup with every table parsed whole (the reader without an index),
  on tables of ``--baseline-scale`` (the whole tables at full size need several GB).

The tables are kept under ``--root`` (default: the temporary folder) and reused by later runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
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

VERSION = "v1.0-trainval"
SCENES = 850  # v1.0-trainval
# per scene: 40 samples at 2 Hz (34,149 / 850), so 19.5 s of sensor data
SAMPLES = 40
CAMERAS = {"CAM_FRONT": 0.0, "CAM_FRONT_LEFT": 55.0, "CAM_FRONT_RIGHT": -55.0, "CAM_BACK": 180.0,
           "CAM_BACK_LEFT": 110.0, "CAM_BACK_RIGHT": -110.0}
RADARS = ("RADAR_FRONT", "RADAR_FRONT_LEFT", "RADAR_FRONT_RIGHT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT")
RATES_HZ = {**{c: 12.0 for c in CAMERAS}, "LIDAR_TOP": 20.0, **{r: 13.0 for r in RADARS}}
INSTANCES, ANNOTATED_SAMPLES = 76, 18  # 64,386 instances, 1,166,187 annotations over 850 scenes
LOGS = 68
CATEGORIES = (
    "human.pedestrian.adult", "human.pedestrian.child", "human.pedestrian.wheelchair",
    "human.pedestrian.stroller", "human.pedestrian.personal_mobility", "human.pedestrian.police_officer",
    "human.pedestrian.construction_worker", "animal", "vehicle.car", "vehicle.motorcycle",
    "vehicle.bicycle", "vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.truck", "vehicle.construction",
    "vehicle.emergency.ambulance", "vehicle.emergency.police", "vehicle.trailer", "movable_object.barrier",
    "movable_object.trafficcone", "movable_object.pushable_pullable", "movable_object.debris",
    "static_object.bicycle_rack")
KINDS = ("vehicle.car", "human.pedestrian.adult", "movable_object.barrier", "vehicle.truck")
T0_US = 1_531_883_530_000_000
LIDAR_POINTS = 34_720  # a nuScenes LIDAR_TOP sweep holds about this many points


def token(kind: int, scene: int, i: int) -> str:
    """32 hex digits like a nuScenes token, unique per (kind, scene, i)."""
    return f"{kind:02x}{scene:06x}{i:024x}"


class TableWriter:
    """One ``<table>.json`` written row by row (the tables never sit in memory whole)."""

    def __init__(self, path: Path):
        self.f = open(path, "w", encoding="utf-8")
        self.f.write("[\n")
        self.rows = 0

    def add(self, row: dict) -> None:
        # one key per line, like the dataset's files (json.dump with indent=0)
        self.f.write((",\n" if self.rows else "") + json.dumps(row, separators=(",\n", ": ")))
        self.rows += 1

    def close(self) -> None:
        self.f.write("\n]\n")
        self.f.close()


def _quat_yaw(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def _ego(t: float, s: int) -> tuple[list[float], list[float]]:
    """Ego pose at ``t`` seconds into scene ``s``: 6 m/s along a gentle curve."""
    yaw = 0.3 * s + 0.01 * t
    x0, y0 = 400.0 + 3.0 * (s % 50), 1100.0 + 2.0 * (s // 50)
    return [x0 + 6.0 * t * math.cos(yaw), y0 + 6.0 * t * math.sin(yaw), 0.0], _quat_yaw(yaw)


def _calibrations(w: dict, s: int) -> dict[str, str]:
    from paradrive import geometry

    # camera axes in the ego frame (OpenCV x right, y down, z forward), turned by the mount's yaw
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    tokens = {}
    for j, channel in enumerate((*CAMERAS, "LIDAR_TOP", *RADARS)):
        tokens[channel] = token(3, s, j)
        if channel in CAMERAS:
            rot = geometry.rotation_about("z", math.radians(CAMERAS[channel])) @ base
            intrinsic = [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]]
        else:
            rot, intrinsic = np.eye(3), []
        w["calibrated_sensor"].add({
            "token": tokens[channel], "sensor_token": token(2, 0, j), "translation": [1.7, 0.0, 1.5],
            "rotation": [float(v) for v in geometry.rotation_to_quaternion(rot)],
            "camera_intrinsic": intrinsic})
    return tokens


def _sensor_data(w: dict, s: int, sample_tokens: list[str], calib: dict[str, str]) -> None:
    """sample_data and ego_pose rows of every channel of scene ``s``."""
    n = 0
    span = (SAMPLES - 1) * 0.5
    for channel, hz in RATES_HZ.items():
        frames = int(span * hz)
        key_every = hz / 2.0
        tokens = [token(4, s, n + i) for i in range(frames)]
        for i in range(frames):
            t = i / hz
            stamp = T0_US + s * 30_000_000 + int(round(t * 1e6))
            k = min(int(round(i / key_every)), SAMPLES - 1)
            keyframe = abs(i - k * key_every) < 0.5
            ext = "jpg" if channel in CAMERAS else ("pcd.bin" if channel == "LIDAR_TOP" else "pcd")
            folder = "samples" if keyframe else "sweeps"
            translation, rotation = _ego(t, s)
            w["ego_pose"].add({"token": token(5, s, n + i), "timestamp": stamp, "rotation": rotation,
                               "translation": translation})
            w["sample_data"].add({
                "token": tokens[i], "sample_token": sample_tokens[k], "ego_pose_token": token(5, s, n + i),
                "calibrated_sensor_token": calib[channel], "timestamp": stamp,
                "fileformat": ext.split(".")[0], "is_key_frame": keyframe,
                "height": 900 if channel in CAMERAS else 0, "width": 1600 if channel in CAMERAS else 0,
                "filename": f"{folder}/{channel}/n015-2018-07-24-11-22-45+0800__{channel}__{stamp}.{ext}",
                "prev": tokens[i - 1] if i else "", "next": tokens[i + 1] if i + 1 < frames else ""})
        n += frames


def _annotations(w: dict, s: int, sample_tokens: list[str]) -> None:
    for j in range(INSTANCES):
        kind = KINDS[j % len(KINDS)]
        first = (j * 7) % (SAMPLES - ANNOTATED_SAMPLES)
        tokens = [token(7, s, j * SAMPLES + k) for k in range(ANNOTATED_SAMPLES)]
        for k in range(ANNOTATED_SAMPLES):
            t = (first + k) * 0.5
            (x, y, _), rotation = _ego(t, s)
            ahead = 8.0 + 2.0 * (j % 9) + (0.0 if kind == "movable_object.barrier" else 2.0 * t)
            w["sample_annotation"].add({
                "token": tokens[k], "sample_token": sample_tokens[first + k],
                "instance_token": token(6, s, j), "visibility_token": "4", "attribute_tokens": [],
                "translation": [x + ahead, y + 3.0 * ((j % 5) - 2), 0.8], "size": [1.9, 4.5, 1.6],
                "rotation": rotation, "prev": tokens[k - 1] if k else "",
                "next": tokens[k + 1] if k + 1 < ANNOTATED_SAMPLES else "",
                "num_lidar_pts": 40, "num_radar_pts": 2})
        w["instance"].add({"token": token(6, s, j), "category_token": token(1, 0, CATEGORIES.index(kind)),
                           "nbr_annotations": ANNOTATED_SAMPLES, "first_annotation_token": tokens[0],
                           "last_annotation_token": tokens[-1]})


def generate(root: Path, scenes: int) -> dict[str, int]:
    """Write the tables of ``scenes`` scenes under ``root/VERSION``; their row counts."""
    meta = root / VERSION
    meta.mkdir(parents=True, exist_ok=True)
    names = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "log",
             "category", "instance", "sample_annotation")
    w = {name: TableWriter(meta / f"{name}.json") for name in names}
    for j, channel in enumerate((*CAMERAS, "LIDAR_TOP", *RADARS)):
        w["sensor"].add({"token": token(2, 0, j), "channel": channel,
                         "modality": "camera" if channel in CAMERAS else channel.split("_")[0].lower()})
    for j, name in enumerate(CATEGORIES):
        w["category"].add({"token": token(1, 0, j), "name": name, "description": ""})
    for j in range(min(LOGS, scenes)):
        w["log"].add({"token": token(8, 0, j), "logfile": f"n015-2018-07-24-11-22-45+0800-{j}",
                      "vehicle": "n015", "date_captured": "2018-07-24", "location": "singapore-onenorth"})
    for s in range(scenes):
        sample_tokens = [token(9, s, k) for k in range(SAMPLES)]
        w["scene"].add({"token": token(10, s, 0), "log_token": token(8, 0, s % min(LOGS, scenes)),
                        "nbr_samples": SAMPLES, "first_sample_token": sample_tokens[0],
                        "last_sample_token": sample_tokens[-1], "name": f"scene-{s:04d}",
                        "description": "generated"})
        for k, tok in enumerate(sample_tokens):
            w["sample"].add({"token": tok, "timestamp": T0_US + s * 30_000_000 + k * 500_000,
                             "prev": sample_tokens[k - 1] if k else "",
                             "next": sample_tokens[k + 1] if k + 1 < SAMPLES else "",
                             "scene_token": token(10, s, 0)})
        _sensor_data(w, s, sample_tokens, _calibrations(w, s))
        _annotations(w, s, sample_tokens)
    for writer in w.values():
        writer.close()
    return {name: writer.rows for name, writer in w.items()}


def place_files(root: Path, scene: int) -> int:
    """One JPEG (1600x900) and one LiDAR sweep linked under every file name of ``scene``."""
    from paradrive.ingest.common import encode_jpeg
    from paradrive.ingest.nuscenes_tables import stream_rows

    rng = np.random.default_rng(0)
    gradient = np.linspace(0, 255, 1600, dtype=np.float32)[None, :, None]
    pixels = np.clip(gradient + rng.normal(0, 4, (900, 1600, 3)), 0, 255).astype(np.uint8)
    jpeg, sweep = root / "image.jpg", root / "sweep.pcd.bin"
    jpeg.write_bytes(encode_jpeg(pixels, 90))
    points = rng.uniform(-50, 50, (LIDAR_POINTS, 5)).astype(np.float32)
    sweep.write_bytes(points.tobytes())
    linked = 0
    marker = f"{scene:06x}"
    for row, _ in stream_rows(root / VERSION / "sample_data.json"):
        if row["token"][2:8] != marker or row["fileformat"] not in ("jpg", "pcd"):
            continue
        target = root / row["filename"]
        if row["fileformat"] == "pcd" and "LIDAR_TOP" not in row["filename"]:
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.exists():
            os.link(jpeg if row["fileformat"] == "jpg" else sweep, target)
        linked += 1
    return linked


def tables_at(root: Path, scale: float, scene: int) -> dict:
    """The generated tables under ``root`` (made on the first run, reused later)."""
    scenes = max(2, round(SCENES * scale))
    done = root / "generated.json"
    if done.is_file() and json.loads(done.read_text()).get("scenes") == scenes:
        return json.loads(done.read_text())
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    t0 = time.perf_counter()
    rows = generate(root, scenes)
    info = {"scenes": scenes, "rows": rows, "generate_seconds": round(time.perf_counter() - t0, 1),
            "json_mb": round(sum(p.stat().st_size for p in (root / VERSION).glob("*.json")) / 2**20),
            "files_linked": place_files(root, min(scene, scenes - 1))}
    done.write_text(json.dumps(info))
    return info


# --------------------------------------------------------------------------- measured in a child

def _peak_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss it does not carry the
    parent's size over the fork before exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return round(int(line.split()[1]) / 1024, 1)
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


class Timed:
    """A tables object whose calls are timed (``seconds``: the time spent reading rows)."""

    def __init__(self, tables):
        self.tables, self.seconds = tables, 0.0

    def __getattr__(self, name):
        call = getattr(self.tables, name)

        def timed(*args):
            t0 = time.perf_counter()
            try:
                return call(*args)
            finally:
                self.seconds += time.perf_counter() - t0
        return timed


def scene_lookup(root: Path, scene: int, tables=None) -> dict:
    """Everything ingest reads and computes from the tables for one scene (no pixels): seconds
    (``rows_seconds`` of them in the tables' own calls, opening the index included) and counts."""
    from paradrive.ingest import nuscenes
    from paradrive.ingest.nuscenes_tables import open_tables
    from paradrive.contracts.params import params_of
    from paradrive.uri import parse_uri

    params = params_of({})
    t0 = time.perf_counter()
    uri = parse_uri(f"nuscenes:{root}?version={VERSION}#scene-{scene:04d}")
    timed = Timed(tables if tables is not None else open_tables(root / VERSION, "bench"))
    opened = time.perf_counter() - t0
    reader = nuscenes._Reader(uri, root, root / "unused", params, "bench", timed)
    cameras = [reader.camera(c) for c in reader.chosen]
    poses = [reader.ego_of(sd) for cam in reader.chosen for sd in reader.chains[cam]]
    lidar = nuscenes.chain(reader.tables, reader.firsts["LIDAR_TOP"], set(reader.samples),
                           scene_id="bench", where=reader.where_sd)
    actors = nuscenes.annotation_actors(reader.tables, reader.samples, reader.stamps, reader.world,
                                        scene_id="bench", meta=reader.meta)
    return {"seconds": round(time.perf_counter() - t0, 4), "rows_seconds": round(opened + timed.seconds, 4),
            "frames": len(reader.clock),
            "cameras": len(cameras), "images": len(poses), "lidar_sweeps": len(lidar),
            "actors": len(actors)}


def child(mode: str, root: Path, scenes: list[int], frames: int) -> dict:
    from paradrive.ingest.nuscenes_tables import JsonTables, open_tables

    meta = root / VERSION
    if mode == "build":
        t0 = time.perf_counter()
        tables = open_tables(meta, "bench")
        out = {"seconds": round(time.perf_counter() - t0, 2), "built_here": tables.built_here,
               "index_mb": round(tables.path.stat().st_size / 2**20)}
    elif mode == "lookup":
        out = {"scenes": [scene_lookup(root, s) for s in scenes]}
    elif mode == "baseline":
        t0 = time.perf_counter()
        tables = JsonTables.load(meta, "bench")
        load = time.perf_counter() - t0
        out = {"load_seconds": round(load, 2), "scene": scene_lookup(root, scenes[0], tables)}
    else:
        from paradrive.stages.ingest import ingest, params_of

        out_dir = Path(tempfile.mkdtemp(prefix="bench-nus-")) / "scene"
        params = params_of({"max_frames": frames or None})
        t0 = time.perf_counter()
        summary = ingest(f"nuscenes:{root}?version={VERSION}#scene-{scenes[0]:04d}", out_dir, params)
        out = {"seconds": round(time.perf_counter() - t0, 1), "frames": summary["frames"],
               "cameras": len(summary["cameras"])}
        shutil.rmtree(out_dir.parent, ignore_errors=True)
    return {**out, "peak_rss_mb": _peak_mb()}


def run_child(mode: str, root: Path, scenes: list[int], frames: int = 0) -> dict:
    cmd = [sys.executable, __file__, "--child", mode, "--root", str(root),
           "--scenes", ",".join(map(str, scenes)), "--ingest-frames", str(frames)]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    result = json.loads(done.stdout.strip().splitlines()[-1])
    print(json.dumps({mode: result}), file=sys.stderr, flush=True)  # progress of a long run
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="fraction of v1.0-trainval's 850 scenes")
    ap.add_argument("--baseline-scale", type=float, default=0.1,
                    help="scenes of the tables read whole, as a fraction of 850 (0 = skip)")
    ap.add_argument("--root", type=Path, default=Path(tempfile.gettempdir()) / "paradrive-bench-nuscenes")
    ap.add_argument("--lookups", type=int, default=5, help="scenes looked up")
    ap.add_argument("--skip-ingest", action="store_true", help="leave out the scene's whole ingest")
    ap.add_argument("--ingest-frames", type=int, default=0,
                    help="frames of the measured ingest (0 = the whole scene, 234 frames of 6 cameras)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--scenes", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.root, [int(s) for s in args.scenes.split(",")],
                               args.ingest_frames)))
        return
    scenes = max(2, round(SCENES * args.scale))
    middle = scenes // 2
    root = args.root / f"scale-{args.scale:g}"
    generated = tables_at(root, args.scale, middle)
    shutil.rmtree(root / VERSION / ".paradrive", ignore_errors=True)
    report = {"bench": "nuscenes_tables", "machine": platform.processor() or platform.machine(),
              "cpus": os.cpu_count(), "scale": args.scale, "generated": generated,
              "build": run_child("build", root, [0])}
    picks = sorted({round(i * (scenes - 1) / max(1, args.lookups - 1)) for i in range(args.lookups)})
    lookups = run_child("lookup", root, picks)
    seconds = [s["seconds"] for s in lookups["scenes"]]
    rows = [s["rows_seconds"] for s in lookups["scenes"]]
    report["lookup"] = {**lookups, "mean_seconds": round(float(np.mean(seconds)), 4),
                        "max_seconds": max(seconds), "rows_mean_seconds": round(float(np.mean(rows)), 4),
                        "rows_max_seconds": max(rows)}
    if not args.skip_ingest:
        report["ingest"] = run_child("ingest", root, [middle], args.ingest_frames)
    if args.baseline_scale > 0:
        base_root = args.root / f"scale-{args.baseline_scale:g}"
        base = tables_at(base_root, args.baseline_scale, 0)
        report["baseline"] = {"scale": args.baseline_scale, "json_mb": base["json_mb"],
                              **run_child("baseline", base_root, [0])}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
