"""A video's masks on the real freeway clip: the time of the ego mask (hood and overlays) and of
the moving masks, and the moving masks against the two cars boxed by hand on eleven frames
(tests/udacity_freeway_cars.json): the share of each car's box pixels masked and of the static
road masked.

The clip (../shared/realdata/udacity-freeway/, beside the repository) is ingested once the
default way (``video:…mp4?calib=calibration.json&height_m=1.23``: every frame, 1280x720,
undistorted), unless ``--scene`` names a scene of it already ingested (any size or rate). Its
masks are then made again in a copy, timed, and scored. The baseline, in the same process:
reading the scene's frames once, as the masks must.

``--busy N`` runs N processes that spin on the CPU while the masks are made (a busy machine).

    .venv/bin/python bench/bench_masks.py --workdir /tmp/bench-masks
    .venv/bin/python bench/bench_masks.py --scene /tmp/bench-masks/freeway --busy 2
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
CLIP = ROOT.parent / "shared" / "realdata" / "udacity-freeway"
LABELS = ROOT / "tests" / "udacity_freeway_cars.json"


def ingest_clip(workdir: Path) -> Path:
    """The clip ingested the default way under ``workdir`` (once); the scene."""
    from paradrive.stages.ingest import ingest, params_of

    scene = workdir / "freeway"
    if not (scene / "scene.json").is_file():
        ingest(f"video:{CLIP / 'freeway-shadows-1280x720.mp4'}?calib=calibration.json&height_m=1.23",
               scene, params_of())
    return scene


def measure(scene_dir: Path) -> dict:
    from paradrive.ingest.videomasks import labelled_scores, write_video_masks
    from paradrive.scene import load_scene

    scene = load_scene(scene_dir)
    n = len(scene.frames)
    start, cpu = time.perf_counter(), time.process_time()
    for k in range(n):
        scene.load_image(k, "front")
    floor = {"seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu}
    record = write_video_masks(lambda k: scene.load_image(k, "front"), scene.c2w("front"), scene.ego2world(),
                               scene.cameras["front"].K(), scene_dir, "front", scene_id=scene.scene_id)
    scores = labelled_scores(scene_dir, LABELS, CLIP / "calibration.json")
    cam = scene.cameras["front"]
    return {
        "frames": n, "size": [cam.width, cam.height],
        "masks": record, "read_frames": {k: round(v, 3) for k, v in floor.items()},
        "cpu_ratio_to_reading": round(record["cpu_seconds"] / max(floor["cpu_seconds"], 1e-9), 1),
        "coverage": round(scores.coverage, 4), "named": {k: round(v, 4) for k, v in scores.named.items()},
        "worst_frame_coverage": round(scores.worst_coverage, 4),
        "road_masked": round(scores.road_masked, 4), "worst_frame_road_masked": round(scores.worst_road_masked, 4),
        "per_frame": {k: [round(c, 3), round(r, 4)] for k, (c, r) in scores.frames.items()},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, help="an ingested scene of the clip (its masks are made again in a copy)")
    ap.add_argument("--workdir", type=Path, default=None, help="where the clip is ingested (kept for --scene)")
    ap.add_argument("--busy", type=int, default=0, help="processes spinning on the CPU meanwhile")
    a = ap.parse_args()
    if a.scene is None and not CLIP.is_dir():
        print(json.dumps({"skipped": f"the clip is not here ({CLIP})"}))
        return 0
    workdir = a.workdir or Path(tempfile.mkdtemp(prefix="bench-masks-"))
    workdir.mkdir(parents=True, exist_ok=True)
    source = a.scene or ingest_clip(workdir)
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / source.name
        shutil.copytree(source, copy, ignore=shutil.ignore_patterns("masks", "lidar"))
        spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(a.busy)]
        try:
            result = measure(copy)
        finally:
            for s in spinners:
                s.kill()
                s.wait()
    result.update({"scene": str(source), "busy": a.busy,
                   "load_average": [round(x, 2) for x in os.getloadavg()]})
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
