"""Scene-graph fit cost: time per iteration of the fit with one node per moving actor against
the static fit of the same scene, side by side in one process; prints JSON.

    .venv/bin/python bench/bench_graph.py [--profile demo] [--iterations 200] [--threads 1]

The synthetic street (moving traffic) is ingested with the profile's parameters; both fits start
from scratch with the profile's fit parameters shortened to ``--iterations`` (densification
included when the profile refines before then). ``cost_ratio`` is the graph fit's seconds per
iteration over the static fit's (goal: at most 1.3). Both fits' Gaussian counts are reported:
the graph's per-iteration work also depends on how many Gaussians each model grows.

A third fit places the nodes with the torch expressions (the path of a CUDA device, or where the
native kernels are not built) instead of the native placement kernels (within float32 rounding):
``placement_speedup`` is its seconds per iteration over the graph fit's, that one the mean of a
run before and a run after it (a shared machine's speed drifts within minutes).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from bench_fit import first_call_seconds, ingest, time_fit  # noqa: E402


@contextmanager
def torch_placement():
    """The scene graph placed by its torch expressions while inside."""
    from paradrive.gs import graph

    native = graph._place_kernels
    graph._place_kernels = lambda *args: None
    try:
        yield
    finally:
        graph._place_kernels = native


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--threads", type=int, default=None, help="override the profile's fit threads")
    args = ap.parse_args()
    from paradrive.contracts.params import params_of

    with tempfile.TemporaryDirectory() as tmp:
        first_call_seconds("cpu")
        scene_dir, params = ingest(args.profile, Path(tmp))
        params.update(checkpoints=[args.iterations], keep_state=False)
        if args.threads is not None:
            params["threads"] = args.threads
        threshold = params_of(None).moving_threshold_m
        static = time_fit(scene_dir, {**params, "dynamic": "off"}, "cpu", label="static",
                          moving_threshold_m=threshold)
        graph = time_fit(scene_dir, {**params, "dynamic": "auto"}, "cpu", label="scene graph",
                         moving_threshold_m=threshold)
        with torch_placement():
            placed = time_fit(scene_dir, {**params, "dynamic": "auto"}, "cpu",
                              label="scene graph, placement as torch operations",
                              moving_threshold_m=threshold)
        again = time_fit(scene_dir, {**params, "dynamic": "auto"}, "cpu", label="scene graph",
                         moving_threshold_m=threshold)
    per_it = [1.0 / r["iterations_per_second"] for r in (static, graph, placed, again)]
    graph_per_it = (per_it[1] + per_it[3]) / 2
    print(json.dumps({"bench": "graph", "machine": platform.machine(), "profile": args.profile,
                      "iterations": args.iterations, "threads": params["threads"],
                      "load_average": [round(x, 2) for x in os.getloadavg()],
                      "runs": [static, graph, placed, again],
                      "cost_ratio": round(graph_per_it / per_it[0], 3),
                      "placement_speedup": round(per_it[2] / graph_per_it, 3)}, indent=2))


if __name__ == "__main__":
    main()
