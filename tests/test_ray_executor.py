"""The Ray executor: (scene, stage) tasks with declared resources, chained per scene, streamed back.

One local Ray (2 CPUs, no GPU) serves the whole module. The stand-in stages of
``pipeline_stages`` declare ``gpu: 1`` for fit and render, so the GPU policy is exercised too.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path

import pytest

from paradrive.errors import ConfigError
from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.executors import make_executor
from paradrive.pipeline.executors import LocalExecutor
from paradrive.pipeline.ledger import Ledger
from paradrive.pipeline.executors.ray import Capacity, RayExecutor, task_resources
from paradrive.pipeline.runner import scene_dir_for
from paradrive.contracts.specs import Resources

import pipeline_stages

ROOT = Path(__file__).resolve().parents[1]
SCENES = [f"synthetic:street?seed={s}" for s in (1, 2, 3)]
GIB = 1024 ** 3


# -- the resource policy (no cluster needed) ----------------------------------------------------

CPU_ONLY = Capacity(cpu=2, gpu=0, memory_bytes=8 * GIB)
WITH_GPU = Capacity(cpu=16, gpu=1, memory_bytes=64 * GIB)


def test_declared_resources_become_task_options():
    opts, warnings = task_resources("fit", Resources(cpu=2, gpu=1, memory_gb=16), WITH_GPU)
    assert opts == {"num_cpus": 2, "num_gpus": 1, "memory": 16 * GIB} and warnings == []


def test_gpu_request_becomes_zero_with_a_warning_on_a_cluster_without_gpu():
    opts, warnings = task_resources("fit", Resources(cpu=2, gpu=1, memory_gb=4), CPU_ONLY)
    assert opts["num_gpus"] == 0
    assert warnings == ["stage 'fit' declares gpu: 1 but the cluster has no GPU; running it on "
                        "CPU (--gpu-policy require refuses instead)"]


def test_gpu_policy_require_refuses_a_cluster_without_gpu():
    with pytest.raises(ConfigError, match="declares gpu: 1 but the Ray cluster has no GPU"):
        task_resources("fit", Resources(gpu=1), CPU_ONLY, "require")
    opts, _ = task_resources("fit", Resources(gpu=1), WITH_GPU, "require")
    assert opts["num_gpus"] == 1


def test_gpu_policy_cpu_never_asks_for_gpus():
    opts, warnings = task_resources("fit", Resources(gpu=1), WITH_GPU, "cpu")
    assert opts["num_gpus"] == 0 and warnings == []


def test_requests_are_capped_to_the_largest_node():
    opts, warnings = task_resources("fit", Resources(cpu=8, gpu=0, memory_gb=16), CPU_ONLY)
    assert opts["num_cpus"] == 2 and opts["memory"] == 8 * GIB
    assert len(warnings) == 2 and "cpu: 8" in warnings[0] and "memory_gb: 16" in warnings[1]


def test_capacity_is_the_largest_alive_node():
    nodes = [{"Alive": True, "Resources": {"CPU": 4.0, "memory": 1e9}},
             {"Alive": True, "Resources": {"CPU": 8.0, "GPU": 2.0, "memory": 5e9}},
             {"Alive": False, "Resources": {"CPU": 64.0, "GPU": 8.0}}]
    assert Capacity.of_nodes(nodes) == Capacity(cpu=8.0, gpu=2.0, memory_bytes=5e9)


def test_unknown_gpu_policy_is_a_usage_error():
    with pytest.raises(ConfigError, match="use one of auto, require, cpu"):
        make_executor("ray", gpu_policy="sometimes")


# -- on a local Ray cluster ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def ray_cluster():
    import ray
    # Workers inherit this environment: they import paradrive and the stand-in stages from here.
    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")] +
                                               ([saved] if saved else []))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved


def build_with(executor, config, root: Path, scenes=SCENES, ledger=True):
    led = Ledger.for_build(root / "manifests", "b") if ledger else None
    if led:
        registry = config.registry()
        led.register(scenes, [s for s in registry.order() if registry.specs[s].scope == "scene"],
                     ["manifest"])
    seen = []

    def on_result(result):
        seen.append(result)
        if led:
            led.record(result)

    report = run_build(config, scenes, root / "data", executor=executor,
                       manifests_dir=root / "manifests", build="b",
                       on_start=led.start if led else None, on_result=on_result)
    return report, seen, led


def test_ray_build_equals_local_build(ray_cluster, stage_config, tmp_path):
    config = stage_config()
    local, _, _ = build_with(LocalExecutor(), config, tmp_path / "local")
    ray_executor = RayExecutor()
    remote, streamed, ledger = build_with(ray_executor, config, tmp_path / "ray")
    assert local.exit_code == remote.exit_code == 0
    assert pipeline_stages.tree_digest(tmp_path / "ray") == pipeline_stages.tree_digest(tmp_path / "local")
    assert (tmp_path / "ray/manifests/b/pairs.jsonl").read_bytes() == \
        (tmp_path / "local/manifests/b/pairs.jsonl").read_bytes()
    # every result reached the driver's callback, and every stage ran in a Ray worker
    assert len(streamed) == len(remote.results) == 3 * 4 + 1
    assert {r.status for r in remote.results} == {"done"}
    pids = {pid for _, stage, _, pid in (line.split() for line in
                                         (tmp_path / "ray/data/calls.log").read_text().splitlines())
            if stage != "manifest"}  # build stages run on the driver
    assert str(os.getpid()) not in pids
    assert {(sid, st) for sid, st in ray_executor.placements} == {
        (f"synthetic-street-s{s}", st) for s in (1, 2, 3) for st in ("ingest", "fit", "render", "clip")}
    assert ledger.scene_states() == {f"synthetic-street-s{s}": "done" for s in (1, 2, 3)}
    # the cluster has no GPU: fit and render (gpu: 1) ran on CPU, with a warning each
    assert sorted(w.split("'")[1] for w in ray_executor.warnings) == ["fit", "render"]


def test_progress_of_tasks_on_the_workers_reaches_the_driver_and_the_scene_logs(
        ray_cluster, stage_config, tmp_path):
    from paradrive.pipeline.progress import StageCounts
    from paradrive.contracts.layout import DataLayout

    snaps, order = [], []
    counts = StageCounts(["ingest", "fit", "render", "clip"], len(SCENES))

    def on_result(result):
        counts.result(result)
        order.append(("result", result.scene_id, result.stage))

    def on_progress(snap):
        snaps.append(snap)
        order.append(("progress", snap.scene_id, snap.stage))

    report = run_build(stage_config(), SCENES, tmp_path / "data", executor=RayExecutor(),
                       manifests_dir=tmp_path / "manifests", build="b", on_start=counts.start,
                       on_result=on_result, on_progress=on_progress)
    assert report.exit_code == 0
    ids = [f"synthetic-street-s{s}" for s in (1, 2, 3)]
    # The stand-in render reports a step per offset on its worker; each one's last step reaches
    # the driver before the task's result does.
    assert sorted((s.scene_id, s.stage, s.done, s.total) for s in snaps if s.done == s.total) == \
        [(sid, "render", 2, 2) for sid in ids]
    for sid in ids:
        assert order.index(("progress", sid, "render")) < order.index(("result", sid, "render"))
        assert "render: frame 2/2 (100%)" in DataLayout(tmp_path / "data").log(sid).read_text()
    assert counts.line() == "ingest 3/3, fit 3/3, render 3/3, clip 3/3"


def test_stages_of_a_scene_run_in_order_and_scenes_in_parallel(ray_cluster, stage_config, tmp_path):
    report, streamed, _ = build_with(RayExecutor(max_in_flight=3), stage_config(), tmp_path, ledger=False)
    order = {}
    for r in streamed:
        order.setdefault(r.scene_id, []).append(r.stage)
    for sid, stages in order.items():
        if sid.startswith("synthetic"):
            assert stages == ["ingest", "fit", "render", "clip"]
    # results interleave across scenes: the first scene is not finished before another started
    first_clip = next(i for i, r in enumerate(streamed) if r.stage == "clip")
    assert len({r.scene_id for r in streamed[:first_clip]}) > 1


def test_max_in_flight_from_the_command_line_bounds_the_tasks_out_at_once(ray_cluster, tmp_path,
                                                                          monkeypatch):
    from typer.testing import CliRunner

    from paradrive.cli import app

    folder = pipeline_stages.write_stages(tmp_path / "stages")
    monkeypatch.setenv("PARADRIVE_STAGES", str(folder))
    args = ["build", *[a for uri in SCENES for a in ("--scene", uri)], "--data", str(tmp_path / "data"),
            "--manifests", str(tmp_path / "manifests"), "--build", "b", "--executor", "ray",
            "--max-in-flight", "1"]
    res = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    events = [c for c in pipeline_stages.calls(tmp_path / "data") if c[2] != "build"]
    assert len(events) == 2 * 4 * len(SCENES)
    # one task at a time: every start is followed by its own end
    assert all(events[i][0] == "start" and events[i + 1] == ("end",) + events[i][1:]
               for i in range(0, len(events), 2))
    res = CliRunner().invoke(app, args[:-1] + ["0"], env={"COLUMNS": "250"})
    assert res.exit_code == 2 and "--max-in-flight" in res.output


def test_a_failed_scene_blocks_only_its_own_later_stages(ray_cluster, stage_config, tmp_path):
    scenes = SCENES[:2] + ["synthetic:street?seed=9&fail=fit"]
    report, _, ledger = build_with(RayExecutor(), stage_config(), tmp_path, scenes=scenes)
    assert report.exit_code == 3
    bad = "synthetic-street-s9-failfit"
    assert ledger.scene_states() == {"synthetic-street-s1": "done", "synthetic-street-s2": "done",
                                     bad: "failed"}
    assert "fit cannot read this scene" in ledger.task(bad, "fit")["error"]
    assert ledger.task(bad, "render")["state"] == ledger.task(bad, "clip")["state"] == "blocked"
    rows = (tmp_path / "manifests/b/pairs.jsonl").read_text()
    assert "synthetic-street-s1" in rows and bad not in rows


def test_a_worker_that_dies_mid_task_is_retried_and_leaves_nothing_half_written(
        ray_cluster, stage_config, tmp_path):
    scenes = SCENES[:1] + ["synthetic:street?seed=5&crash=render"]
    report, _, ledger = build_with(RayExecutor(max_retries=1), stage_config(), tmp_path, scenes=scenes)
    assert report.exit_code == 0
    crashed = "synthetic-street-s5-crashrender"
    assert (tmp_path / "data" / f"crashed-{crashed}-render").is_file()  # it did die once
    scene_dir = scene_dir_for(tmp_path / "data", crashed)
    assert not list(scene_dir.rglob(".*.tmp-*")), "the retry removes what the dead worker left"
    starts = [c for c in pipeline_stages.calls(tmp_path / "data") if c[:2] == ("start", "render")
              and c[2] == crashed]
    assert len(starts) == 2
    # the driver handed the task out twice, and the ledger counts both tries
    assert ledger.task(crashed, "render")["attempts"] == 2
    assert ledger.task(crashed, "fit")["attempts"] == 1


def test_a_task_lost_for_good_is_a_failure_and_the_rerun_finishes_only_it(
        ray_cluster, stage_config, tmp_path):
    scenes = SCENES[:2] + ["synthetic:street?seed=5&crash=fit"]
    crashed = "synthetic-street-s5-crashfit"
    report, _, ledger = build_with(RayExecutor(max_retries=0), stage_config(), tmp_path, scenes=scenes)
    assert report.exit_code == 3
    row = ledger.task(crashed, "fit")
    assert row["state"] == "failed" and "lost on the Ray cluster" in row["error"]
    assert ledger.failed_scene_uris() == [scenes[2]]
    before = len(pipeline_stages.finished(tmp_path / "data"))
    # the re-run (the crash happens only once) completes exactly the missing work
    report, _, ledger = build_with(RayExecutor(max_retries=0), stage_config(), tmp_path, scenes=scenes)
    assert report.exit_code == 0
    redone = pipeline_stages.finished(tmp_path / "data")[before:]
    assert sorted(redone) == sorted([("clip", crashed), ("fit", crashed), ("render", crashed),
                                     ("manifest", "build")])


def test_a_stage_that_cannot_be_imported_on_the_workers_fails_with_its_reason(
        ray_cluster, stage_config, tmp_path):
    config = stage_config()
    folder = Path(config.stages_dir)
    text = (folder / "clip.yaml").read_text().replace("pipeline_stages:run_clip",
                                                      "pipeline_stages_missing:run_clip")
    (folder / "clip.yaml").write_text(text)
    config = StageRegistry(folder).resolve()
    report, _, ledger = build_with(RayExecutor(), config, tmp_path, scenes=SCENES[:1])
    assert report.exit_code == 1  # its only scene failed at clip: no scene landed
    assert "implementation pipeline_stages_missing:run_clip is not available" in \
        ledger.task("synthetic-street-s1", "clip")["error"]


# -- the real pipeline, local and Ray, through the command line ---------------------------------

REAL_SCENES = [f"synthetic:demo?seed={s}" for s in (1, 2)]
CORRUPT = "synthetic:demo?seed=4&colour=red"  # an option the synthetic reader does not know


def _normalised_index(build_dir: Path, root: Path) -> str:
    doc = json.loads((build_dir / "index.json").read_text().replace(str(root), "<root>"))
    doc.pop("created_at")
    return json.dumps(doc, sort_keys=True)


@pytest.mark.slow
def test_real_pipeline_on_ray_equals_local_and_a_corrupt_scene_makes_a_partial_build(
        ray_cluster, s3_bucket, tmp_path, monkeypatch):
    """Local executor to a folder, Ray to a folder, Ray to S3: the same rows and the same bytes."""
    from typer.testing import CliRunner

    from paradrive.cli import app
    from paradrive.pairs import read_pairs
    from paradrive.storage import DataRoot

    monkeypatch.delenv("PARADRIVE_STAGES", raising=False)
    listing = tmp_path / "scenes.txt"
    listing.write_text("# two good scenes and a bad one\n" + "\n".join(REAL_SCENES + [CORRUPT]) + "\n")
    sets = pipeline_stages.tiny_real_sets()
    url = "s3://builds/smoke3"
    storage = [arg for key, value in s3_bucket.items()
               for arg in ("--storage-option", f"{key}={json.dumps(value)}")]
    runs = {"local": ("local", []), "ray": ("ray", []), "ray-s3": ("ray", [
        "--data", url, *storage, "--cache", str(tmp_path / "cache")])}
    for name, (executor, where) in runs.items():
        root = tmp_path / name
        res = CliRunner().invoke(app, ["build", "--scenes", str(listing), "--profile", "smoke", *sets,
                                       "--data", str(root / "data"), "--manifests",
                                       str(root / "manifests"), "--build", "smoke3",
                                       "--executor", executor, *where], env={"COLUMNS": "250"})
        assert res.exit_code == 3, res.output  # partial: the good scenes landed, the bad one did not
        assert "2 of 3 scenes done; exit code 3 (partial build)" in res.output
        ledger = Ledger.for_build(root / "manifests", "smoke3")
        states = ledger.scene_states()
        assert states.pop("synthetic-demo-s4-colourred") == "failed"
        assert set(states.values()) == {"done"} and len(states) == 2
        row = ledger.task("synthetic-demo-s4-colourred", "ingest")
        assert "unknown synthetic option 'colour'" in row["error"]
        assert ledger.runs()[-1]["executor"] == executor

    local = tmp_path / "local"
    rows = read_pairs(local / "manifests" / "smoke3").to_pylist()
    assert {r["scene_id"] for r in rows} == {f"synthetic-demo-s{s}" for s in (1, 2)}
    # the scenes written to S3, fetched back into a folder shaped like the others
    s3 = DataRoot.of(url, storage_options=s3_bucket)
    fs, base = s3.filesystem()
    fetched = tmp_path / "ray-s3" / "data"
    for name in fs.find(f"{base}/scenes"):
        target = fetched / name[len(base) + 1:]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(fs.cat_file(name))
    skip = (".paradrive", "logs", "locks", "ledger.sqlite", "index.json", "fit.json")
    expected = pipeline_stages.tree_digest(local, skip)
    for name in ("ray", "ray-s3"):
        other = tmp_path / name
        assert read_pairs(other / "manifests" / "smoke3").to_pylist() == rows
        index = _normalised_index(other / "manifests" / "smoke3", other).replace(url, "<root>/data")
        assert index == _normalised_index(local / "manifests" / "smoke3", local)
        # every file byte for byte (checkpoints, renders, videos, shards), but the clocks in fit.json
        assert pipeline_stages.tree_digest(other, skip) == expected
        for s in (1, 2):
            rel = Path("data/scenes") / f"synthetic-demo-s{s}" / "gs" / "fit.json"
            assert _without_clocks(other / rel) == _without_clocks(local / rel)
    markers = fs.find(f"{base}/scenes/synthetic-demo-s1/.paradrive")
    assert sorted(m.rsplit("/", 1)[1] for m in markers) == [
        "clip.json", "fit.json", "ingest.json", "render.json"]
    assert not fs.exists(f"{base}/scenes/synthetic-demo-s4-colourred/scene.json")


def _without_clocks(path: Path):
    def strip(obj):
        if isinstance(obj, dict):
            return {k: strip(v) for k, v in obj.items()
                    if k not in ("seconds", "cpu_seconds", "peak_rss_mb")}
        if isinstance(obj, list):
            return [strip(v) for v in obj]
        return obj
    return strip(json.loads(path.read_text()))


def test_gpu_policy_require_refuses_the_cpu_only_test_cluster_before_running_anything(
        ray_cluster, stage_config, tmp_path):
    with pytest.raises(ConfigError, match="stage 'fit' declares gpu: 1 but the Ray cluster has no GPU"):
        build_with(RayExecutor(gpu_policy="require"), stage_config(), tmp_path, ledger=False)
    assert pipeline_stages.calls(tmp_path / "data") == []


@pytest.mark.slow
def test_a_ray_build_killed_midway_resumes_with_only_the_missing_work(tmp_path):
    """SIGKILL to the driver of a real-stage Ray build (its local cluster goes with it), then the
    same command again: what had landed is skipped, the rest is done, the result is the same."""
    import signal
    import subprocess
    import sys

    import psutil
    scenes = REAL_SCENES[:2]
    ids = [f"synthetic-demo-s{s}" for s in (1, 2)]
    listing = tmp_path / "scenes.txt"
    listing.write_text("\n".join(scenes) + "\n")
    env = {k: v for k, v in os.environ.items() if k != "PARADRIVE_STAGES"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))

    def command(root: Path, executor: str) -> list[str]:
        return [sys.executable, "-m", "paradrive.cli", "build", "--scenes", str(listing),
                "--profile", "smoke", *pipeline_stages.tiny_real_sets(), "--data", str(root / "data"),
                "--manifests", str(root / "manifests"), "--build", "b", "--executor", executor]

    whole = tmp_path / "whole"
    done = subprocess.run(command(whole, "local"), env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]

    killed = tmp_path / "killed"
    # the driver stops itself once the first scene's fit has landed, with work still to do
    proc = subprocess.Popen(command(killed, "ray"), env={**env, "PARADRIVE_STOP_AT": f"landed:fit:{ids[0]}"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), "the build ended before the kill"
        # SIGKILL to the driver and the local cluster it started (same process group), at once
        group = [p for p in psutil.process_iter(["pid"]) if _process_group(p.pid) == proc.pid]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    # every process of the group is gone (psutil waits on each until it has exited)
    psutil.wait_procs(group)
    left = [p for p in psutil.process_iter(["pid", "status"]) if _process_group(p.pid) == proc.pid
            and p.info["status"] != psutil.STATUS_ZOMBIE]
    assert not left, f"processes of the killed build still run: {left}"
    ledger = Ledger.for_build(killed / "manifests", "b")
    assert ledger.runs()[-1]["exit_code"] is None  # the dead build never finished its run
    landed = {(sid, p.stem) for sid in ids
              for p in (scene_dir_for(killed / "data", sid) / ".paradrive").glob("*.json")}
    assert (ids[0], "fit") in landed and len(landed) < 8, landed

    resumed = subprocess.run(command(killed, "ray"), env=env, capture_output=True, text=True,
                             timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    # what the re-run did with each (scene, stage), as it says it (the ledger keeps "done" for a
    # stage the killed run finished)
    states = {(m[3], m[2]): m[1] for m in re.finditer(r"^\s*(skipped|done)\s+(\w+)\s+(\S+) \(",
                                                          resumed.stderr, re.M)
              if not m[3].startswith("build:")}
    assert len(states) == 8, resumed.stderr[-3000:]
    # A worker of the killed cluster may still finish the stage it had begun: it holds that
    # scene's lock, so the new build waits for it and then finds the stage done, not redoing it.
    skipped = {k for k, v in states.items() if v == "skipped"}
    assert landed <= skipped and len(skipped - landed) <= 1, (landed, skipped)
    assert {k for k, v in states.items() if v == "done"} == set(states) - skipped
    skip = (".paradrive", "logs", "locks", "ledger.sqlite", "index.json", "fit.json")
    assert pipeline_stages.tree_digest(killed, skip) == pipeline_stages.tree_digest(whole, skip)
    assert not list((killed / "data").rglob(".*.tmp-*"))


def _process_group(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except OSError:
        return None


@pytest.mark.parametrize("where", ["folder", "s3"])
def test_two_ray_builds_at_once_over_shared_scenes_run_each_stage_once(ray_cluster, stage_config,
                                                                      where, tmp_path, request):
    """Two builds started together on one cluster (threads of one driver), scene lists that
    overlap in opposite orders, into one data root: each (scene, stage) runs once, the files are
    those of a build of the scenes alone."""
    import threading

    from paradrive.storage import DataRoot

    config = stage_config({"fit": {"sleep_s": 0.5}})
    if where == "folder":
        root = DataRoot.of(tmp_path / "data")
    else:
        root = DataRoot.of(f"s3://builds/ray-{where}-{os.getpid()}", cache_dir=str(tmp_path / "cache"),
                           storage_options=request.getfixturevalue("s3_bucket"))
    lists = {"b1": SCENES, "b2": SCENES[::-1]}
    reports = {}

    def run(build):
        reports[build] = run_build(config, lists[build], root, executor=RayExecutor(),
                                   manifests_dir=tmp_path / "m", build=build)

    threads = [threading.Thread(target=run, args=(b,)) for b in lists]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert {b: r.exit_code for b, r in reports.items()} == {"b1": 0, "b2": 0}, \
        [f.error for r in reports.values() for f in r.failures()]
    ran = [k for k in pipeline_stages.finished(root.local) if k[1] != "build"]
    assert sorted(ran) == sorted((st, f"synthetic-street-s{s}") for s in (1, 2, 3)
                                 for st in ("ingest", "fit", "render", "clip"))
    alone, _, _ = build_with(LocalExecutor(), stage_config({"fit": {"sleep_s": 0.5}}),
                             tmp_path / "alone", ledger=False)
    assert alone.exit_code == 0
    assert pipeline_stages.scenes_digest(root) == \
        pipeline_stages.tree_digest(tmp_path / "alone" / "data" / "scenes")
    rows = {b: sorted((tmp_path / "m" / b / "pairs.jsonl").read_text().splitlines()) for b in lists}
    assert rows["b1"] == rows["b2"] and len(rows["b1"]) == 3 * 2  # in their own scene order
