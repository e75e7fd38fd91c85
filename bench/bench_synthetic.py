"""Synthetic street render speed at 480x832, against a cast that tests every ray against every object.

Run: python bench/bench_synthetic.py [--frames 24] [--naive-frames 2] [--threads 2]
Prints one JSON object. The naive baseline (no screen-rectangle culling, no occlusion skipping)
is measured in the same process on the same first frames, single-threaded like the culled run it
is compared with, and its output is checked to be identical. CPU seconds are reported next to
wall seconds because wall time on a shared machine depends on its load.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from paradrive.synthetic import SyntheticStreet


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24, help="frames rendered for the timing")
    ap.add_argument("--naive-frames", type=int, default=2)
    ap.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--width", type=int, default=832)
    ap.add_argument("--height", type=int, default=480)
    args = ap.parse_args()
    w, h, n, nf = args.width, args.height, args.frames, args.naive_frames

    street, build_s, _ = timed(lambda: SyntheticStreet(seed=7, frames=160, width=w, height=h))
    K = street.cameras["front"].K()
    c2w = street.c2w("front")[:n]
    # every other frame shifted 3 m left: the pipeline renders both kinds of pose
    ego = street.ego2world()[:n]
    move = np.eye(4)
    move[1, 3] = 3.0
    poses = c2w.copy()
    poses[1::2] = ego[1::2] @ move @ np.linalg.inv(ego[1::2]) @ c2w[1::2]

    street.render(poses[:1], K, w, h)  # warm up
    _, wall, cpu = timed(lambda: street.render(poses, K, w, h, threads=args.threads))
    fast, fast_wall, fast_cpu = timed(lambda: street.render(poses[:nf], K, w, h, threads=1))
    naive, naive_wall, naive_cpu = timed(lambda: street.render(poses[:nf], K, w, h, threads=1,
                                                               cull=False))
    identical = all(np.array_equal(fast[k], naive[k]) for k in ("rgb", "depth", "sky"))
    _, lidar_wall, lidar_cpu = timed(lambda: [street.lidar_points(i) for i in range(5)])

    print(json.dumps({
        "resolution": [h, w],
        "frames": n,
        "threads": args.threads,
        "objects": int(len(street.prims.boxes) + len(street.prims.cylinders) + len(street.prims.spheres)),
        "build_s": round(build_s, 3),
        "seconds_per_frame": round(wall / n, 4),
        "cpu_seconds_per_frame": round(cpu / n, 4),
        "projected_121_frames_s": round(121 * wall / n, 2),
        "single_thread_seconds_per_frame": round(fast_wall / nf, 4),
        "naive_seconds_per_frame": round(naive_wall / nf, 4),
        "speedup_vs_naive": round(naive_wall / fast_wall, 2),
        "speedup_vs_naive_cpu": round(naive_cpu / fast_cpu, 2),
        "naive_output_identical": bool(identical),
        "lidar_seconds_per_scan": round(lidar_wall / 5, 4),
        "lidar_cpu_seconds_per_scan": round(lidar_cpu / 5, 4),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
    }, indent=1))


if __name__ == "__main__":
    main()
