"""The build-level work at many scenes: publish, inspect, status, plan, a no-op re-run, the
adapter's construction and a Ray build of near-empty stages; prints JSON (and writes ``--out``).

    .venv/bin/python bench/bench_scale.py --scenes 50 [--out scale-50.json] [--workdir /tmp/s]
    .venv/bin/python bench/bench_scale.py --scenes 1600 --workdir /work/tmp/scale  # the paper's size

Scenes. One synthetic scene is built by the real stages (the smoke profile with a fit of 8
iterations): 614 files, 72 pairs, 36 clips. It is then copied under ``--scenes`` new ids
(``synthetic:demo?seed=<1000+i>``): every file is hard-linked, the records that name the scene
(``scene.json``, ``gs/fit.json``, ``renders/renders.json``, ``clips/clips.json``) are loaded and
saved through their own types with the new id, and each stage's marker gets the new id, URI and
fingerprint from :func:`paradrive.pipeline.runner.stage_fingerprint`, the records that changed
listed anew by :func:`paradrive.pipeline.runner.output_entry`. The ledger is filled through
:class:`paradrive.pipeline.ledger.Ledger` (register, start and record each stage), as a build
fills it. A no-op re-run of the copies must
skip every stage: the bench asserts it, so the copies are what the runner would have made.

Measures. Each operation runs in a fresh Python process: ``seconds`` is the operation itself
(timed inside the process, imports excluded; ``cpu_s`` the CPU time it took in that process,
which a loaded machine disturbs less), ``process_s`` the whole process, ``peak_mb`` the
process's resident high-water mark during the operation (reset after the imports; ``base_mb``
is what was resident when it started, ``idle`` a process that only imports the CLI),
``children_peak_mb`` its largest child's (a DataLoader worker, ``ru_maxrss``). Commands run through the CLI's own
functions (``paradrive build --stages manifest``, ``inspect --verify``, ``inspect --json``,
``status --json``, ``plan --json``, ``build``). The Ray run uses a stage folder
(``PARADRIVE_STAGES``) of two stages that each write one small file, on a local Ray started
before the clock starts; ``per_task_ms`` is its wall time over the tasks it ran.

Sizes are tiny (8-frame 160x96 clips), so the figures are the bookkeeping's, not the media's:
hashing a paper-size scene's clips is extra (``media_bytes`` says how many bytes were hashed).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TEMPLATE_URI = "synthetic:demo?seed=7"
PROFILE = "smoke"
# The smoke profile with a fit of 8 iterations: the scene's files and pairs, seconds to build.
OVERRIDES = {
    "fit": {"checkpoints": [2, 4, 6, 8], "refine_start_iter": 2, "refine_every": 2,
            "refine_stop_iter": 6, "state_interval": 4, "init_points": 500, "sky_points": 100},
    "render": {"condition_checkpoints": [2, 4, 6], "source_checkpoint": 8},
}
BUILD = "scale"
RAY_STAGES = {
    "first": "name: first\nentry: scale_stages:run\nneeds: []\nresources: {cpu: 1, gpu: 0, memory_gb: 0}\n"
             "outputs: [\"first.txt\"]\nparams:\n  tag: {default: first, doc: \"file written\"}\n",
    "second": "name: second\nentry: scale_stages:run\nneeds: [first]\nresources: {cpu: 1, gpu: 0, memory_gb: 0}\n"
              "outputs: [\"second.txt\"]\nparams:\n  tag: {default: second, doc: \"file written\"}\n",
}
RAY_MODULE = '''"""Near-empty stages: each writes one small file, so a build measures the scheduling."""
from paradrive.io import write_text


def run(ctx):
    write_text(ctx.layout.root / f"{ctx.params['tag']}.txt", ctx.scene_id)
    return {}
'''


def set_args() -> list[str]:
    """``OVERRIDES`` as the CLI's ``--set`` options."""
    return [a for stage, params in OVERRIDES.items() for name, value in params.items()
            for a in ("--set", f"{stage}.{name}={json.dumps(value)}")]


def config():
    from paradrive.pipeline import StageRegistry

    return StageRegistry().resolve(PROFILE, OVERRIDES)


def scene_uri(i: int) -> str:
    return f"synthetic:demo?seed={1000 + i}"


# --------------------------------------------------------------------------- the scenes

def build_template(work: Path) -> Path:
    """One scene through every scene stage; its folder."""
    from paradrive.pipeline import run_build
    from paradrive.pipeline.build import split_stages
    from paradrive.uri import parse_uri

    cfg = config()
    report = run_build(cfg, [TEMPLATE_URI], work / "template", stages=split_stages(cfg, None)[0],
                       manifests_dir=work / "template-manifests", build="template")
    assert not report.failures(), [r.error for r in report.failures()]
    return work / "template" / "scenes" / parse_uri(TEMPLATE_URI).scene_id


def clone_scene(cfg, template: Path, data: Path, uri: str) -> Path:
    """The template scene under ``uri``'s id: hard links, re-tagged records, markers anew."""
    from paradrive.contracts.layout import MARKER_DIR, SceneLayout
    from paradrive.pipeline.runner import (marker_path, output_entry, read_marker,
                                           stage_fingerprint)
    from paradrive.uri import parse_uri

    sid = parse_uri(uri).scene_id
    dst = SceneLayout.of(data, sid).root
    for src in template.rglob("*"):
        rel = src.relative_to(template)
        if src.is_dir() or rel.parts[0] == MARKER_DIR:
            continue
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        os.link(src, dst / rel)
    changed = _retag(dst, template, sid, uri)
    for stage in cfg.registry().order(None):
        marker = read_marker(template, stage)
        if marker is None:
            continue
        fp, upstream = stage_fingerprint(cfg, stage, uri, dst)
        outputs = dict(marker.outputs or {})
        outputs.update((rel, output_entry(dst / rel)) for rel in changed if rel in outputs)
        marker.model_copy(update={"scene_id": sid, "scene_uri": uri, "fingerprint": fp,
                                  "inputs": {k: v.fingerprint for k, v in upstream.items()},
                                  "outputs": outputs}).save(marker_path(dst, stage))
    return dst


def _retag(dst: Path, template: Path, sid: str, uri: str) -> list[str]:
    """Save the scene's records under the new id through their own types (each lands by rename,
    so the hard link to the template's file is replaced, never written through); their paths."""
    from paradrive.contracts.layout import SceneLayout
    from paradrive.contracts.records import ClipsRecord, FitRecord, RendersRecord
    from paradrive.scene import load_scene, write_scene

    new, old = SceneLayout(dst), SceneLayout(template)
    scene = load_scene(new.root, check_files=False)
    write_scene(dataclasses.replace(scene, scene_id=sid, source=uri), new.root)
    FitRecord.load(old.fit_json).model_copy(update={"scene_id": sid}).save(new.fit_json)
    RendersRecord.load(old.renders_json).model_copy(update={"scene_id": sid}).save(new.renders_json)
    ClipsRecord.load(old.clips_json).model_copy(
        update={"scene_id": sid, "source": uri}).save(new.clips_json)
    return [p.relative_to(dst).as_posix()
            for p in (new.scene_json, new.fit_json, new.renders_json, new.clips_json)]


def fill_ledger(cfg, manifests: Path, uris: list[str], template: Path) -> float:
    """The ledger rows a build of ``uris`` leaves (each scene stage done, with the template's
    seconds), written through the ledger's API; returns the seconds it took."""
    from paradrive.pipeline.build import split_stages
    from paradrive.pipeline.ledger import Ledger
    from paradrive.pipeline.runner import StageResult, read_marker
    from paradrive.uri import parse_uri

    scene_stages, build_stages = split_stages(cfg, None)
    seconds = {s: getattr(read_marker(template, s), "seconds", None) or 0.0 for s in scene_stages}
    t0 = time.perf_counter()
    ledger = Ledger.for_build(manifests, BUILD)
    ledger.register(uris, scene_stages, build_stages)
    ledger.begin_run("local", len(uris))
    for uri in uris:
        sid = parse_uri(uri).scene_id
        for stage in scene_stages:
            ledger.start(uri, stage)
            ledger.record(StageResult(sid, stage, "done", seconds=seconds[stage], peak_rss_mb=300.0))
    ledger.end_run(0)
    ledger.close()
    return time.perf_counter() - t0


def make_scenes(work: Path, n: int) -> dict:
    cfg = config()
    t0 = time.perf_counter()
    template = build_template(work)
    built = time.perf_counter() - t0
    data, manifests = work / "data", work / "manifests"
    uris = [scene_uri(i) for i in range(n)]
    t0 = time.perf_counter()
    for uri in uris:
        clone_scene(cfg, template, data, uri)
    cloned = time.perf_counter() - t0
    (work / "scenes.txt").write_text("".join(u + "\n" for u in uris))
    ledger_s = fill_ledger(cfg, manifests, uris, template)
    return {"template_s": round(built, 2), "clone_s": round(cloned, 2),
            "ledger_fill_s": round(ledger_s, 2),
            "files_per_scene": sum(1 for p in template.rglob("*") if p.is_file())}


# --------------------------------------------------------------------------- operations (child side)

def _cli(args: list[str]) -> int:
    """Run ``paradrive ARGS`` in this process, its output discarded; its exit code."""
    from paradrive.cli import app

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            app(args, standalone_mode=False)
        except SystemExit as exc:
            return int(exc.code or 0)
        except BaseException as exc:  # click's Exit carries the code
            code = getattr(exc, "exit_code", None)
            if code is None:
                raise
            return int(code)
    return 0


def _common(work: Path) -> list[str]:
    return ["--data", str(work / "data"), "--manifests", str(work / "manifests"), "--build", BUILD,
            "--profile", PROFILE, *set_args()]


def op_publish(work: Path) -> dict:
    code = _cli(["build", "--scenes", str(work / "scenes.txt"), "--stages", "manifest", *_common(work)])
    assert code == 0, f"publish exited {code}"
    index = json.loads((work / "manifests" / BUILD / "index.json").read_text())
    return {"rows": index["totals"]["rows"], "media_files": index["totals"]["media_files"],
            "media_bytes": index["totals"]["media_bytes"]}


def op_verify(work: Path) -> dict:
    code = _cli(["inspect", str(work / "manifests" / BUILD), "--verify", "--json"])
    assert code == 0, f"inspect --verify exited {code}"
    return {}


def op_inspect(work: Path) -> dict:
    code = _cli(["inspect", str(work / "manifests" / BUILD), "--json"])
    assert code == 0, f"inspect exited {code}"
    return {}


def op_status(work: Path) -> dict:
    code = _cli(["status", BUILD, "--manifests", str(work / "manifests"), "--json"])
    assert code == 0, f"status exited {code}"
    return {}


def op_plan(work: Path) -> dict:
    code = _cli(["plan", "--scenes", str(work / "scenes.txt"), "--data", str(work / "data"),
                 "--profile", PROFILE, *set_args(), "--json"])
    assert code == 0, f"plan exited {code}"
    return {}


def _scene_state(data: Path) -> dict[str, tuple[int, int]]:
    """Every marker and record of every scene: size and mtime (what a stage that ran changes)."""
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns)
            for pattern in ("*/.paradrive/*.json", "*/clips/clips.json", "*/scene.json")
            for p in (data / "scenes").glob(pattern)}


def op_rerun(work: Path) -> dict:
    from paradrive.pipeline.ledger import Ledger

    before = _scene_state(work / "data")
    code = _cli(["build", "--scenes", str(work / "scenes.txt"), *_common(work)])
    assert code == 0, f"the no-op re-run exited {code}"
    assert _scene_state(work / "data") == before, "the no-op re-run changed a scene"
    ledger = Ledger.open_existing(work / "manifests", BUILD)
    states = {(r["scene_id"], r["stage"]): r["state"] for r in ledger.tasks()}
    ran = sorted(k for k, s in states.items() if s != "skipped")
    assert not ran, f"the no-op re-run did not skip {ran[:5]}"
    return {"skipped": len(states)}


def op_adapter(work: Path) -> dict:
    from paradrive.data import PairDataset, PairIterableDataset

    build = work / "manifests" / BUILD
    t0 = time.perf_counter()
    ds = PairDataset(build, num_frames=4, dtype="uint8")
    made = time.perf_counter() - t0
    t0 = time.perf_counter()
    ds[len(ds) // 2]
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    it = PairIterableDataset(build, num_frames=4, dtype="uint8", seed=1)
    made_it = time.perf_counter() - t0
    t0 = time.perf_counter()
    next(iter(it))
    first_it = time.perf_counter() - t0
    return {"rows": len(ds), "construct_s": round(made, 3), "first_sample_s": round(first, 3),
            "iterable_construct_s": round(made_it, 3), "iterable_first_sample_s": round(first_it, 3)}


def op_loader(work: Path) -> dict:
    """A DataLoader with 2 workers: the time to one sample from each (each worker's copy of the
    dataset is built here and pickled to it, as a trainer does)."""
    from torch.utils.data import DataLoader

    from paradrive.data import PairIterableDataset

    ds = PairIterableDataset(work / "manifests" / BUILD, num_frames=4, dtype="uint8", seed=1)
    t0 = time.perf_counter()
    loader = iter(DataLoader(ds, batch_size=None, num_workers=2))
    next(loader)
    next(loader)
    return {"first_per_worker_s": round(time.perf_counter() - t0, 3)}


def op_idle(work: Path) -> dict:
    import paradrive.cli  # noqa: F401  (what every command imports)

    return {}


def write_ray_stages(work: Path) -> Path:
    folder = work / "ray-stages"
    (folder / "profiles").mkdir(parents=True, exist_ok=True)
    for name, text in RAY_STAGES.items():
        (folder / f"{name}.yaml").write_text(text)
    (work / "ray-module").mkdir(exist_ok=True)
    (work / "ray-module" / "scale_stages.py").write_text(RAY_MODULE)
    return folder


def op_ray(work: Path) -> dict:
    import ray

    from paradrive.pipeline import StageRegistry, run_build
    from paradrive.pipeline.executors.ray import RayExecutor

    uris = (work / "scenes.txt").read_text().split()
    cfg = StageRegistry().resolve(None)
    env = {"PYTHONPATH": os.environ["PYTHONPATH"], "PARADRIVE_STAGES": os.environ["PARADRIVE_STAGES"]}
    ray.init(include_dashboard=False, log_to_driver=False, num_cpus=os.cpu_count(),
             runtime_env={"env_vars": env})
    results: list = []
    try:
        executor = RayExecutor()
        t0 = time.perf_counter()
        report = run_build(cfg, uris, work / "ray-data", executor=executor,
                           manifests_dir=work / "ray-manifests", build="ray",
                           on_result=results.append)
        seconds = time.perf_counter() - t0
    finally:
        ray.shutdown()
    failed = report.failures()
    assert not failed, [r.error for r in failed[:3]]
    assert all(r.status == "done" for r in results), "a Ray task was skipped or failed"
    window = max(2, 2 * (os.cpu_count() or 1))
    return {"tasks": len(results), "per_task_ms": round(1000 * seconds / len(results), 2),
            "in_flight": window}


OPERATIONS = {"idle": op_idle, "publish": op_publish, "inspect_verify": op_verify,
              "inspect": op_inspect, "status": op_status, "plan": op_plan, "rerun_noop": op_rerun,
              "adapter": op_adapter, "adapter_loader": op_loader, "ray": op_ray}


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _memory_mb(field: str) -> float:
    """``VmRSS`` (resident now) or ``VmHWM`` (resident high-water) of this process, in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"/proc/self/status has no {field}")


def child(op: str, work: Path) -> None:
    """The child side: run one operation, print its figures as one JSON line. The high-water
    mark is reset after the imports (``/proc/self/clear_refs``), so ``peak_mb`` is the
    operation's own peak (what the imports left resident included, ``base_mb``)."""
    if op != "idle":
        import paradrive.cli  # noqa: F401  (imports are not the operation's time)
    Path("/proc/self/clear_refs").write_text("5")
    base = _memory_mb("VmRSS")
    cpu0, t0 = _cpu_s(), time.perf_counter()
    extra = OPERATIONS[op](work)
    seconds, cpu = time.perf_counter() - t0, _cpu_s() - cpu0
    workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # KB on Linux
    print(json.dumps({"seconds": round(seconds, 4), "cpu_s": round(cpu, 3),
                      "peak_mb": round(_memory_mb("VmHWM"), 1), "base_mb": round(base, 1),
                      **({"children_peak_mb": round(workers, 1)} if workers else {}), **extra}))


# --------------------------------------------------------------------------- parent side

def measure(op: str, work: Path, env: dict | None = None) -> dict:
    """Run ``op`` in a fresh process; its figures with the process's wall time."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", op, "--workdir", str(work)],
                          capture_output=True, text=True, env={**os.environ, **(env or {})})
    if proc.returncode != 0:  # recorded, and the other operations still run
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"error": f"exit {proc.returncode}: {last}", "process_s": round(time.perf_counter() - t0, 2)}
    return {**json.loads(proc.stdout.strip().splitlines()[-1]),
            "process_s": round(time.perf_counter() - t0, 2)}


def machine() -> dict:
    import torch

    return {"cpus": os.cpu_count(), "load_avg": [round(x, 2) for x in os.getloadavg()],
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "python": platform.python_version(), "platform": platform.platform()}


def run(n: int, work: Path, ops: list[str]) -> dict:
    result = {"bench": "scale", "scenes": n, "machine": machine(), "setup": make_scenes(work, n)}
    ray_env = {"PARADRIVE_STAGES": str(write_ray_stages(work)),
               "PYTHONPATH": os.pathsep.join([str(work / "ray-module"), str(REPO)])}
    figures = {}
    for op in ops:
        figures[op] = measure(op, work, ray_env if op == "ray" else None)
        print(f"{op}: {figures[op]}", file=sys.stderr)
    result["operations"] = figures
    result["machine"]["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=50)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--workdir", type=Path, default=None,
                        help="where the scenes go (default: a temporary folder); emptied first, removed after")
    parser.add_argument("--ops", default=",".join(OPERATIONS),
                        help="comma-separated operations, in order (publish comes before the ones reading the build)")
    parser.add_argument("--keep", action="store_true", help="keep the work folder")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.workdir)
        return
    work = args.workdir or Path(tempfile.mkdtemp(prefix="paradrive-scale-"))
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    try:
        result = run(args.scenes, work, args.ops.split(","))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    text = json.dumps(result, indent=2)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
