"""Throughput of the trainer's adapter (paradrive.data) on pairs of 3 x 121 frames at the demo's
320x192 and the paper's 480x832, and its construction over a 115K-row build.

Makes its own builds: synthetic moving frames encoded by the clip stage's encoder
(``paradrive.video.encode_video``, H.264 yuv420p, CRF 18) behind a real clips.json and a real
manifest, so it runs anywhere. Prints JSON, per frame size, every speed in samples/s (one sample =
the source, condition and target videos of a pair) and, where it says so, as a ratio to a
baseline measured in the same run:

* baseline: every frame of the three files of a pair decoded by bare PyAV to ``rgb24`` arrays
  (``frame.to_ndarray(format="rgb24")``, stacked; the floor any loader pays), with one decoder
  thread (``thread_count=1``, what the adapter uses in DataLoader workers; swscale, which
  ``to_ndarray`` runs, keeps PyAV's default of all cores), with one decoder and one swscale
  thread (``one_thread_scaler_too``: the stricter floor on a busy machine) and with PyAV's own
  threading defaults;
* per_worker: ``PairDataset[i]`` in one process (what each DataLoader worker does), uint8,
  float32 and bfloat16 output, one decoder thread, against the one-thread baseline (goals: uint8
  >= 0.9x, float32 >= 0.6x), in the steady state after a first, untimed sample (reported
  apart); float32 also with ``reuse_buffers=False`` (every sample in fresh memory);
* decode_threads: the same in-process uint8 read with FFmpeg's frame + slice threads
  (``decode_threads=0``) against the baseline with PyAV's defaults;
* dataloader: a torch DataLoader over the dataset with 0 and 2 workers (its collate copies each
  sample once more; with workers into shared memory), uint8 and float32;
* a 25-frame window at the end of the clip, with the x264 default GOP (250) and a 30-frame GOP:
  samples/s and the frames the decoder produced per sample (seeking starts at the keyframe
  before the window, not at frame 0: a full decode is 3 x 121);
* the share of a trainer step spent waiting for data, for an assumed step time
  (``--step-seconds``; the adapter cannot measure the trainer), and the workers needed to keep up;
* with ``--busy``: a CPU-bound process spinning numpy on every core for the whole run, and only
  the baselines and the per-worker cases (the adapter in the main process, as a trainer with
  ``num_workers=0`` or a tool reading pairs runs it): what a machine whose cores are taken by
  other work leaves the adapter. Torch keeps its default intra-op threads in every case
  (``--torch-threads`` sets them): the adapter must not depend on its caller pinning them;
* construction: the rows of a build (the bench's own, or ``--rows-from``) copied under new scene
  ids up to ``--rows`` (72 pairs x 1,600 scenes), then ``PairIterableDataset`` built in a fresh
  interpreter: seconds, peak resident memory, and the dataset pickled as a DataLoader hands it
  to a spawned worker; opened with each shard's sha256 checked against the index (the default)
  and without (``verify_shards=False``), and the ratio of the two (``--construction-only``:
  this case alone).

Usage: python bench/bench_data.py [--pairs 4] [--frames 121] [--sizes 192x320,480x832]
       [--rows 115200] [--rows-from BUILD] [--busy] [--torch-threads N] [--construction-only]
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from spinners import every_core  # noqa: E402  (bench/, the script's own folder)

from paradrive import geometry  # noqa: E402
from paradrive.pairs import build_file  # noqa: E402
from paradrive.pipeline import StageRegistry  # noqa: E402
from paradrive.stages.manifest import build_manifest  # noqa: E402
from paradrive.video import encode_video  # noqa: E402


def synthetic_frames(seed: int, n: int, h: int, w: int):
    """A textured scene panning sideways: realistic enough for the codec to do real work."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 255, (h // 16 + 2, (w + 4 * n) // 16 + 2, 3), dtype=np.uint8)
    big = np.repeat(np.repeat(coarse, 16, axis=0), 16, axis=1).astype(np.float32)
    y, x = np.mgrid[0:h, 0:w]
    shade = (0.6 + 0.4 * np.sin(x / 37.0 + seed) * np.cos(y / 23.0))[..., None]
    for i in range(n):
        yield np.clip(big[:h, 4 * i:4 * i + w] * shade, 0, 255).astype(np.uint8)


def encode(path: Path, frames, fps: int = 10, gop: int | None = None) -> dict:
    """H.264 yuv420p at the clip stage's CRF through its own encoder (the demo profile's preset)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    info = encode_video(path, frames, fps, crf=18, preset="fast", gop=gop)
    return {"bytes": info["bytes"], "sha256": info["sha256"]}


def make_build(root: Path, pairs: int, n: int, h: int, w: int, gop: int | None) -> Path:
    """One scene, one clip: a target, one condition and ``pairs`` shifted sources."""
    scene = root / "data" / "scenes" / "bench"
    ego = np.stack([geometry.translation(x=float(i)) for i in range(n)])
    cam2ego = geometry.make_pose(geometry.OPENCV_TO_FLU, [1.5, 0, 1.6])
    c2w = ego @ cam2ego
    streams = {}
    streams["target"] = {"file": "clips/front/middle/target.mp4", "kind": "target",
                         **encode(scene / "clips/front/middle/target.mp4",
                                  synthetic_frames(0, n, h, w), gop=gop)}
    streams["cond@000100"] = {"file": "clips/front/middle/cond@000100.mp4", "kind": "condition",
                              "iteration": 100,
                              **encode(scene / "clips/front/middle/cond@000100.mp4",
                                       synthetic_frames(1, n, h, w), gop=gop)}
    for k in range(pairs):
        d = float(k + 1) * (1 if k % 2 == 0 else -1)
        name = f"source{d:+g}m"
        shifted = geometry.lateral_shift(c2w, ego, d)
        streams[name] = {"file": f"clips/front/middle/{name}.mp4", "kind": "source",
                         "iteration": 30000, "offset_m": d,
                         "c2w": [m.reshape(16).tolist() for m in shifted],
                         **encode(scene / f"clips/front/middle/{name}.mp4",
                                  synthetic_frames(2 + k, n, h, w), gop=gop)}
    doc = {"schema_version": 1, "scene_id": "bench", "dataset": "synthetic", "source": "bench",
           "fps": 10.0, "width": w, "height": h, "codec": "libx264", "skipped": [],
           "cameras": {"front": {"intrinsics": [w * 0.8, w * 0.8, w / 2, h / 2]}},
           "fit": {"iteration": 30000, "train_psnr": 30.0, "train_ssim": 0.9},
           "clips": [{"camera": "front", "clip": "middle", "frame_start": 0, "num_frames": n,
                      "frame_indices": list(range(n)), "timestamps_us": [i * 100_000 for i in range(n)],
                      "c2w": [m.reshape(16).tolist() for m in c2w], "streams": streams,
                      "quality": {"cond@000100": {"psnr": 20.0, "ssim": 0.6}}}]}
    (scene / "clips" / "clips.json").write_text(json.dumps(doc))
    build = root / "manifests" / "bench"
    params = StageRegistry().resolve(None, {"manifest": {"quality": False}}).typed("manifest")
    build_manifest(build, [{"scene_id": "bench", "scene_dir": str(scene)}], params)
    return build


def timed(samples: int, run) -> dict:
    """Wall and CPU seconds per sample of ``run()`` (CPU: this process and its finished children,
    the DataLoader workers), which handles ``samples`` samples; returns ``run``'s result too."""
    before, t0 = os.times(), time.perf_counter()
    result = run()
    wall, after = time.perf_counter() - t0, os.times()
    cpu = sum(getattr(after, k) - getattr(before, k)
              for k in ("user", "system", "children_user", "children_system"))
    return {"wall": wall / samples, "cpu": cpu / samples, "result": result}


def baseline(build: Path, threads: int | None, scaler_threads: int | None = None) -> dict:
    """Every frame of the three files of each pair decoded to RGB arrays by bare PyAV.

    threads: decoder threads (1 = one); None leaves PyAV's defaults. scaler_threads: swscale's
    threads in ``to_ndarray`` (None: PyAV's default, all cores)."""
    convert = {} if scaler_threads is None else {"threads": scaler_threads}
    import av

    from paradrive.data import PairDataset

    ds = PairDataset(build)
    files = [[build_file(build, ds.row(i)[f"{role}_uri"], "bench", ds.index)
              for role in ("source", "condition", "target")] for i in range(len(ds))]

    def run() -> None:
        for pair in files:
            for path in pair:
                with av.open(str(path)) as c:
                    stream = c.streams.video[0]
                    if threads is not None:
                        stream.codec_context.thread_count = threads
                    np.stack([f.to_ndarray(format="rgb24", **convert) for f in c.decode(stream)])

    return timed(len(files), run)


def loader(build: Path, workers: int, **options) -> dict:
    """Through a torch DataLoader (batch 1) with ``workers`` worker processes."""
    from torch.utils.data import DataLoader

    from paradrive.data import PairDataset

    ds = PairDataset(build, **options)
    batches = DataLoader(ds, batch_size=1, num_workers=workers, persistent_workers=False,
                         prefetch_factor=2 if workers else None)
    return timed(len(ds), lambda: sum(1 for _ in batches))


def in_process(build: Path, **options) -> dict:
    """PairDataset[i] called directly (no DataLoader, no collate copy), in a worker's steady state:
    one sample is read first, untimed (a worker's first sample fills fresh frame buffers, later
    ones reuse them; its seconds are ``first_sample``). ``result``: the frames the decoder
    produced per timed sample."""
    from paradrive.data import PairDataset

    ds = PairDataset(build, **options)
    t0 = time.perf_counter()
    ds[len(ds) - 1]
    first = time.perf_counter() - t0
    ds.frames_decoded = 0

    def run() -> None:
        for i in range(len(ds)):
            ds[i]

    measured = timed(len(ds), run)
    measured["result"] = ds.frames_decoded / len(ds)
    measured["first_sample"] = first
    return measured


def best_of(rounds: int, cases: dict) -> dict:
    """Each case measured ``rounds`` times, the rounds interleaved (a shared machine's load then
    hits every case alike); the fastest wall and the least CPU per case."""
    best: dict = {}
    for _ in range(rounds):
        for name, run in cases.items():
            m = run()
            b = best.setdefault(name, m)
            b["wall"], b["cpu"] = min(b["wall"], m["wall"]), min(b["cpu"], m["cpu"])
    return best


def ratio(m: dict, base: dict) -> dict:
    return {"samples_per_s": round(1 / m["wall"], 3), "ratio_to_baseline": round(base["wall"] / m["wall"], 3),
            "cpu_seconds_per_sample": round(m["cpu"], 3), "cpu_ratio_to_baseline": round(base["cpu"] / m["cpu"], 3)}


# --------------------------------------------------------------------------- construction at scale

def replicate_build(small: Path, dest: Path, rows: int, shard_rows: int = 4096,
                    row_group_rows: int = 64) -> Path:
    """A build of ``rows`` pairs made of ``small``'s rows copied under new scene ids.

    Copy k renames the scene in every pair id, scene id and media URI (so every copy's URIs are
    its own: from the bench's 4-row build, 1.5 distinct URIs a row, three times a real build's
    share; the media need not exist, construction never opens them) and keeps every other
    column, the per-frame poses included. The index lists one scene per 72 rows, as a real
    build's does; shards and row groups are sized as the manifest stage writes them by default.
    """
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from paradrive.contracts.records import IndexRecord
    from paradrive.pairs import SCHEMA, read_index, read_pairs

    index = read_index(small)
    base = read_pairs(small)
    scene = base.column("scene_id")[0].as_py()
    renamed = ("pair_id", "scene_id", "source_uri", "condition_uri", "target_uri")

    def copy(k: int) -> pa.Table:
        new = f"{scene}-{k:05d}"
        cols = {name: (pc.replace_substring(base.column(name), scene, new) if name in renamed
                       else base.column(name)) for name in base.column_names}
        return pa.table(cols, schema=SCHEMA)

    table = pa.concat_tables([copy(k) for k in range(math.ceil(rows / base.num_rows))]).slice(0, rows)
    version = dest / "v-000001"
    version.mkdir(parents=True)
    shards = []
    for i, start in enumerate(range(0, rows, shard_rows)):
        shard, name = table.slice(start, shard_rows), f"pairs-{i:05d}.parquet"
        pq.write_table(shard, version / name, compression="zstd", row_group_size=row_group_rows)
        ids, data = shard.column("pair_id"), (version / name).read_bytes()
        shards.append({"file": name, "rows": shard.num_rows, "bytes": len(data),
                       "sha256": hashlib.sha256(data).hexdigest(), "first_pair_id": ids[0].as_py(),
                       "last_pair_id": ids[-1].as_py()})
    doc = index.model_dump()
    scenes = [{**doc["scenes"][0], "scene_id": f"{scene}-{k:05d}"} for k in range(math.ceil(rows / 72))]
    doc.update(version="v-000001", shards=shards, scenes=scenes,
               totals={**doc["totals"], "rows": rows, "shards": len(shards), "scenes": len(scenes),
                       "shard_bytes": sum(s["bytes"] for s in shards)})
    IndexRecord.model_validate(doc).save(dest / "index.json")
    return dest


_PEAK_MB = """
def peak_mb():
    # VmHWM: this interpreter's own peak (ru_maxrss keeps the parent's across exec)
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmHWM")) / 1024
"""

_CONSTRUCT = _PEAK_MB + """
import json, pickle, sys, time
sys.path.insert(0, {root!r})
import torch
from paradrive.data import PairIterableDataset

before = peak_mb()
t0, c0 = time.perf_counter(), time.process_time()
ds = PairIterableDataset({build!r}, num_frames=121, dtype="uint8", verify_shards={verify!r})
built, cpu = time.perf_counter() - t0, time.process_time() - c0
t0 = time.perf_counter()
blob = pickle.dumps(ds)
pickled = time.perf_counter() - t0
with open({blob!r}, "wb") as out:
    out.write(blob)
print(json.dumps({{"rows": len(ds.dataset), "construct_seconds": round(built, 3),
                  "construct_cpu_seconds": round(cpu, 3),
                  "peak_rss_mb_before": round(before), "peak_rss_mb": round(peak_mb()),
                  "pickled_mb": round(len(blob) / 2**20, 1), "pickle_seconds": round(pickled, 2)}}))
"""

_WORKER = _PEAK_MB + """
import json, pickle, sys, time
sys.path.insert(0, {root!r})
import torch
import paradrive.data

before = peak_mb()
with open({blob!r}, "rb") as blob:
    data = blob.read()
t0 = time.perf_counter()
ds = pickle.loads(data)
unpickled = time.perf_counter() - t0
assert len(ds.dataset) > 0
print(json.dumps({{"worker_unpickle_seconds": round(unpickled, 2), "worker_peak_rss_mb_before": round(before),
                  "worker_peak_rss_mb": round(peak_mb())}}))
"""


_HASH = """
import json, sys, time
sys.path.insert(0, {root!r})
from paradrive.pairs import check_shards, read_index

index = read_index({build!r})
t0 = time.perf_counter()
check_shards({build!r}, index)
print(json.dumps({{"hash_seconds": round(time.perf_counter() - t0, 3)}}))
"""


def construction(build: Path, rounds: int = 3) -> dict:
    """``PairIterableDataset`` over ``build`` built in a fresh interpreter (seconds, its peak
    resident memory before, with torch imported, and after), then pickled as a DataLoader hands
    it to a spawned worker, and unpickled in another fresh interpreter: what a worker holds.

    Opened ``rounds`` times each with the shards' sha256 checked (the default) and without
    (``verify_shards=False``), interleaved, in fresh interpreters (each hashes every shard: the
    check is cached per process); the fastest of each counts, and their ratio is the check's
    cost. The check alone (``check_shards`` over the build, in a fresh interpreter) gives the
    hashing rate. The shards are in the page cache (just written), as a trainer's are after its
    first epoch, so the figure is the hashing, not the disk."""
    root = str(Path(__file__).resolve().parents[1])
    shard_bytes = sum(p.stat().st_size for p in build.glob("v-*/pairs-*.parquet"))
    with tempfile.TemporaryDirectory() as tmp:
        blob = str(Path(tmp) / "dataset.pickle")
        out: dict = {}
        seconds: dict[bool, list[float]] = {True: [], False: []}
        cpu: dict[bool, list[float]] = {True: [], False: []}
        hashing = []
        for _ in range(rounds):
            done = subprocess.run([sys.executable, "-c", _HASH.format(root=root, build=str(build))],
                                  capture_output=True, text=True, check=True)
            hashing.append(json.loads(done.stdout)["hash_seconds"])
            for verify in (False, True):
                code = _CONSTRUCT.format(root=root, build=str(build), blob=blob, verify=verify)
                done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                      check=True)
                found = json.loads(done.stdout)
                seconds[verify].append(found["construct_seconds"])
                cpu[verify].append(found["construct_cpu_seconds"])
                out.update(found if verify else {})
        done = subprocess.run([sys.executable, "-c", _WORKER.format(root=root, blob=blob)],
                              capture_output=True, text=True, check=True)
        out.update(json.loads(done.stdout))
    verified, unverified = min(seconds[True]), min(seconds[False])
    out.update(construct_seconds=verified, construct_seconds_unverified=unverified,
               verify_ratio=round(verified / max(unverified, 1e-9), 2),
               construct_cpu_seconds=min(cpu[True]), construct_cpu_seconds_unverified=min(cpu[False]),
               verify_cpu_ratio=round(min(cpu[True]) / max(min(cpu[False]), 1e-9), 2),
               construct_rounds={"verified": seconds[True], "unverified": seconds[False]},
               shard_mb=round(shard_bytes / 2**20, 1), hash_seconds=min(hashing),
               hash_mb_per_s=round(shard_bytes / 2**20 / max(min(hashing), 1e-9)))
    return out


def size_cases(build: Path, short: Path, frames: int, workers: list[int], busy: bool = False) -> dict:
    """Every case measured at one frame size (see the module's docstring); ``busy``: only the
    baselines and the adapter in this process."""
    window = {"num_frames": 25, "frame_offset": frames - 25, "dtype": "uint8"}
    same_process = {
        "baseline_one_thread": lambda: baseline(build, threads=1),
        "baseline_one_thread_scaler_too": lambda: baseline(build, threads=1, scaler_threads=1),
        **{f"per_worker_{name}": functools.partial(in_process, build, dtype=name)
           for name in ("uint8", "float32", "bfloat16")},
    }
    if busy:
        return same_process
    return {
        **same_process,
        "baseline_pyav_default_threads": lambda: baseline(build, threads=None),
        "per_worker_float32_fresh_buffers": lambda: in_process(build, dtype="float32",
                                                               reuse_buffers=False),
        "uint8_decode_threads_0": lambda: in_process(build, dtype="uint8", decode_threads=0),
        **{f"dataloader_{name}_workers_{k}": functools.partial(loader, build, k, dtype=name)
           for name in ("uint8", "float32") for k in workers},
        "window_x264_default_gop": lambda: in_process(build, **window),
        "window_gop_30": lambda: in_process(short, **window),
    }


def size_report(m: dict, frames: int, step: float) -> dict:
    """One frame size's figures: samples/s, and ratios to the bare decode with the same threads
    (the per-worker uint8 case also against the baseline with a one-thread swscale)."""
    base = m["baseline_one_thread"]
    out: dict = {"baseline": {name[len("baseline_"):]: {"samples_per_s": round(1 / b["wall"], 3),
                                                        "cpu_seconds_per_sample": round(b["cpu"], 3)}
                              for name, b in m.items() if name.startswith("baseline_")}}
    out["per_worker"] = {name[len("per_worker_"):]: {**ratio(v, base),
                                                     "first_sample_seconds": round(v["first_sample"], 3)}
                         for name, v in m.items() if name.startswith("per_worker_")}
    out["per_worker"]["uint8_against_scaler_one_thread"] = ratio(m["per_worker_uint8"],
                                                                 m["baseline_one_thread_scaler_too"])
    out["per_worker"]["goals"] = {"uint8": 0.9, "float32": 0.6}
    if "baseline_pyav_default_threads" not in m:   # --busy: the same-process cases only
        return out
    base_threaded = m["baseline_pyav_default_threads"]
    out["decode_threads_0"] = {"uint8": ratio(m["uint8_decode_threads_0"], base_threaded),
                               "baseline": "pyav_default_threads"}
    out["dataloader"] = {name[len("dataloader_"):]: ratio(v, base) for name, v in m.items()
                         if name.startswith("dataloader_")}
    out["window_25_frames_at_end"] = {
        name[len("window_"):]: {"samples_per_s": round(1 / m[name]["wall"], 3),
                                "frames_decoded_per_sample": round(m[name]["result"], 1),
                                "frames_in_the_three_files": 3 * frames}
        for name in ("window_x264_default_gop", "window_gop_30")}
    t_sample = m["per_worker_uint8"]["wall"]
    best = min(v["wall"] for name, v in m.items() if name.startswith("dataloader_uint8"))
    out["trainer_step_estimate"] = {
        "assumed_step_seconds": step,
        "uint8_data_seconds_per_sample_one_process": round(t_sample, 3),
        "share_of_step_without_workers": round(t_sample / (t_sample + step), 3),
        "workers_to_hide_loading": math.ceil(t_sample / step),
        "stall_share_with_best_uint8_loader": round(max(0.0, best - step) / max(best, step), 3),
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--frames", type=int, default=121)
    ap.add_argument("--sizes", default="192x320,480x832",
                    help="HxW frame sizes, comma-separated (the demo's clips, the paper's)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds; the best of each case counts")
    ap.add_argument("--workers", default="0,2")
    ap.add_argument("--rows", type=int, default=115200,
                    help="rows of the build whose construction is measured (72 pairs x 1,600 "
                         "scenes; 0 = skip)")
    ap.add_argument("--rows-from", type=Path, default=None,
                    help="a build whose rows are copied for --rows (default: the bench's own)")
    ap.add_argument("--step-seconds", type=float, default=3.0,
                    help="assumed trainer step time for one sample (a video diffusion model on "
                         "one GPU at 121x480x832; the adapter cannot measure it)")
    ap.add_argument("--busy", action="store_true",
                    help="a CPU-bound process on every core during the measurements; the "
                         "same-process cases only")
    ap.add_argument("--torch-threads", type=int, default=0,
                    help="torch intra-op threads (0 = torch's default, as a trainer has them)")
    ap.add_argument("--construction-only", action="store_true",
                    help="only the construction at --rows (the rows of a build at the first of "
                         "--sizes, or --rows-from), verified and not")
    args = ap.parse_args()
    import torch

    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    out: dict = {"pairs": args.pairs, "frames": args.frames, "cpus": os.cpu_count(),
                 "rounds": args.rounds, "torch_threads": torch.get_num_threads(), "busy": args.busy,
                 "load_average_before": [round(v, 2) for v in os.getloadavg()],
                 "machine": platform.machine(), "python": platform.python_version(), "sizes": {}}
    workers = [int(x) for x in args.workers.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        if args.construction_only:
            h, w = (int(v) for v in args.sizes.split(",")[0].split("x"))
            build = args.rows_from or make_build(Path(tmp) / "rows", args.pairs, args.frames, h, w,
                                                 gop=None)
        for size in [] if args.construction_only else args.sizes.split(","):
            h, w = (int(v) for v in size.split("x"))
            t0 = time.perf_counter()
            build = make_build(Path(tmp) / size / "default_gop", args.pairs, args.frames, h, w, gop=None)
            short = make_build(Path(tmp) / size / "gop30", args.pairs, args.frames, h, w, gop=30)
            setup = round(time.perf_counter() - t0, 1)
            cases = size_cases(build, short, args.frames, workers, busy=args.busy)
            with every_core(args.busy) as spinners:
                m = best_of(args.rounds, cases)
            out["sizes"][size] = {"setup_seconds": setup, "competing_processes": spinners,
                                  **size_report(m, args.frames, args.step_seconds)}
        if args.rows and not args.busy:
            small = args.rows_from or build
            large = replicate_build(small, Path(tmp) / "large", args.rows)
            out["construction"] = {"rows_copied_from": str(small), **construction(large, args.rounds)}
        out["load_average_after"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
