"""Tiny stand-in stages for the pipeline tests: the real stages' shape, milliseconds of work.

``write_stages(folder)`` writes a stage folder (ingest -> fit -> render -> clip -> manifest) whose
entries are the functions below. Every output is a pure function of the scene URI and the
parameters, so two builds of the same scenes give byte-identical files. Every call appends
``<event> <stage> <scene_id> <pid>`` to ``<data>/calls.log`` (O_APPEND, safe across processes),
so a test can count what ran. The render stage reports its progress (``ctx.progress``) once per
offset.

A scene URI may ask for trouble: ``?fail=<stage>`` makes that stage raise a SceneError;
so does a file ``<data>/broken-<scene_id>-<stage>`` (a fault a
test can repair); ``?crash=<stage>`` kills the process running that stage the first time (a dying worker), after
leaving a temporary file behind as a half-written output would.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import threading
import time
from pathlib import Path

from paradrive.errors import SceneError
from paradrive.io import stop_point, temporary_name, write_json, write_text
from paradrive.uri import parse_uri

STAGES = {
    "ingest": """
name: ingest
entry: pipeline_stages:run_ingest
needs: []
resources: {cpu: 1, gpu: 0, memory_gb: 1}
outputs: ["scene.json", "images"]
params:
  synthetic_frames: {default: 4, doc: "frames written"}
""",
    "fit": """
name: fit
entry: pipeline_stages:run_fit
needs: [ingest]
resources: {cpu: 1, gpu: 1, memory_gb: 1}
outputs: ["gs/ckpt_{checkpoints:06d}.txt", "gs/fit.json"]
params:
  checkpoints: {default: [1, 2], doc: "checkpoints written"}
  sleep_s: {default: 0.0, doc: "seconds to sleep before writing (to kill a build midway)"}
""",
    "render": """
name: render
entry: pipeline_stages:run_render
needs: [fit]
resources: {cpu: 1, gpu: 1, memory_gb: 1}
outputs: ["renders/renders.json"]
params:
  offsets_m: {default: [1.0, -1.0], doc: "lateral offsets rendered"}
""",
    "clip": """
name: clip
entry: pipeline_stages:run_clip
needs: [render]
resources: {cpu: 1, gpu: 0, memory_gb: 1}
outputs: ["clips/clips.json"]
params:
  crf: {default: 18, doc: "quality knob"}
""",
    "manifest": """
name: manifest
entry: pipeline_stages:run_manifest
needs: [clip]
scope: build
resources: {cpu: 1, gpu: 0, memory_gb: 1}
params:
  shard_rows: {default: 100, doc: "rows per shard"}
""",
}


def write_stages(folder: Path) -> Path:
    folder = Path(folder)
    (folder / "profiles").mkdir(parents=True, exist_ok=True)
    for name, text in STAGES.items():
        (folder / f"{name}.yaml").write_text(text.lstrip())
    return folder


def calls(data_dir: Path) -> list[tuple[str, str, str]]:
    """(event, stage, scene_id) of every call so far, in order."""
    path = Path(data_dir) / "calls.log"
    if not path.is_file():
        return []
    return [tuple(line.split()[:3]) for line in path.read_text().splitlines() if line.strip()]


def finished(data_dir: Path) -> list[tuple[str, str]]:
    """(stage, scene_id) of every call that finished its work."""
    return [(stage, sid) for event, stage, sid in calls(data_dir) if event == "end"]


def _note(ctx, event: str, stage: str, sid: str) -> None:
    fd = os.open(Path(ctx.data_dir) / "calls.log", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, f"{event} {stage} {sid} {os.getpid()}\n".encode())
    finally:
        os.close(fd)


def _digest(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _trouble(ctx, stage: str) -> None:
    query = parse_uri(ctx.scene_uri).query
    if query.get("fail") == stage or (Path(ctx.data_dir) / f"broken-{ctx.scene_id}-{stage}").exists():
        raise SceneError(f"{stage} cannot read this scene (asked to fail)", scene_id=ctx.scene_id,
                         path=ctx.scene_uri, fix="drop the scene")
    sentinel = Path(ctx.data_dir) / f"crashed-{ctx.scene_id}-{stage}"
    if query.get("crash") == stage and not sentinel.exists():
        sentinel.write_text("crashed once\n")
        half = temporary_name(ctx.scene_dir / "half-written.bin")
        half.write_bytes(b"\0" * 100)
        os._exit(1)


def hold(data_dir: Path, scene_id: str, stage: str) -> Path:
    """Makes ``stage`` of ``scene_id`` stop once it has started, in every build over
    ``data_dir`` until the returned switch (a named pipe) is removed: it says ``held`` on the
    pipe and waits there, so a test kills it inside the stage, never too late."""
    fifo = Path(data_dir) / f"hold-{scene_id}-{stage}"
    fifo.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(fifo)
    return fifo


def wait_for_hold(fifo: Path, proc: subprocess.Popen) -> str:
    """``held`` once the stage behind ``fifo`` holds; ``ended`` if ``proc`` ends before."""
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    # a writer of our own: the pipe never reads as closed before the first word, and the
    # watcher below answers through it when the process ends first
    writer = os.open(fifo, os.O_WRONLY)
    os.set_blocking(reader, True)
    lock, answered = threading.Lock(), []

    def on_exit() -> None:
        proc.wait()
        with lock:
            if not answered:
                os.write(writer, b"ended\n")

    threading.Thread(target=on_exit, daemon=True).start()
    pipe = os.fdopen(reader)
    word = pipe.readline().strip()
    with lock:
        answered.append(word)
        os.close(writer)
    pipe.close()
    return word


def _hold_here(ctx, stage: str) -> None:
    fifo = Path(ctx.data_dir) / f"hold-{ctx.scene_id}-{stage}"
    if fifo.exists():
        with open(fifo, "w") as pipe:
            pipe.write("held\n")
        threading.Event().wait()   # until killed


def _stage(stage: str):
    def wrap(func):
        def run(ctx):
            _note(ctx, "start", stage, ctx.scene_id)
            _hold_here(ctx, stage)
            _trouble(ctx, stage)
            summary = func(ctx)
            _note(ctx, "end", stage, ctx.scene_id)
            return summary
        run.__name__ = func.__name__
        return run
    return wrap


@_stage("ingest")
def run_ingest(ctx) -> dict:
    frames = ctx.params["synthetic_frames"]
    doc = {"scene_id": ctx.scene_id, "source": ctx.scene_uri, "frames": frames}
    for i in range(frames):
        write_text(ctx.scene_dir / "images" / f"{i:06d}.txt", _digest(ctx.scene_uri, i) + "\n")
    write_json(ctx.scene_dir / "scene.json", doc)
    return {"frames": frames}


@_stage("fit")
def run_fit(ctx) -> dict:
    stop_point("stand-in:fit")   # a test stops the build here, holding the scene's lock
    time.sleep(float(ctx.params["sleep_s"]))
    scene = (ctx.scene_dir / "scene.json").read_text()
    for c in ctx.params["checkpoints"]:
        write_text(ctx.scene_dir / "gs" / f"ckpt_{c:06d}.txt", _digest(scene, c) + "\n")
    write_json(ctx.scene_dir / "gs" / "fit.json", {"psnr": 30.0, "checkpoints": ctx.params["checkpoints"]})
    return {"checkpoints": len(ctx.params["checkpoints"])}


@_stage("render")
def run_render(ctx) -> dict:
    ckpts = sorted((ctx.scene_dir / "gs").glob("ckpt_*.txt"))
    fit = _digest(*[p.read_text() for p in ckpts])
    offsets = ctx.params["offsets_m"]
    files = {}
    for i, d in enumerate(offsets):
        rel = f"renders/{d:+.0f}m.txt"
        write_text(ctx.scene_dir / rel, _digest(fit, d) + "\n")
        files[f"{d:+.1f}"] = rel
        ctx.progress(i + 1, len(offsets))
    write_json(ctx.scene_dir / "renders" / "renders.json", {"offsets_m": offsets, "files": files})
    return {"renders": len(offsets)}


@_stage("clip")
def run_clip(ctx) -> dict:
    renders = json.loads((ctx.scene_dir / "renders" / "renders.json").read_text())
    streams = {k: _digest((ctx.scene_dir / rel).read_text(), ctx.params["crf"])
               for k, rel in renders["files"].items()}
    write_json(ctx.scene_dir / "clips" / "clips.json", {"streams": streams})
    return {"clips": len(streams)}


def run_manifest(ctx) -> dict:
    rows = []
    for scene in ctx.scenes:
        clips = json.loads((Path(scene["scene_dir"]) / "clips" / "clips.json").read_text())
        for offset, digest in sorted(clips["streams"].items()):
            rows.append({"pair_id": f"{scene['scene_id']}/{offset}", "scene_id": scene["scene_id"],
                         "offset_m": float(offset), "clip": digest})
    write_text(ctx.build_dir / "pairs.jsonl", "".join(json.dumps(r) + "\n" for r in rows))
    write_json(ctx.build_dir / "index.json", {"config_fingerprint": ctx.fingerprint,
                                              "rows": len(rows), "scenes": len(ctx.scenes)})
    _note(type("C", (), {"data_dir": ctx.data_dir})(), "end", "manifest", "build")
    return {"rows": len(rows)}


def tree_digest(root: Path, skip=(".paradrive", "logs", "locks", "calls.log", "crashed-", "broken-",
                                  "hold-", "ledger.sqlite")) -> dict[str, str]:
    """sha256 of every file under ``root`` (relative path -> digest), minus bookkeeping files."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and not any(part.startswith(skip) for part in rel.split("/")):
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def scenes_digest(root) -> dict[str, str]:
    """:func:`tree_digest` of a data root's ``scenes/``, a folder or a URL
    (:class:`~paradrive.storage.DataRoot`), markers left out."""
    if not root.remote:
        return tree_digest(root.local / "scenes")
    fs, base = root.filesystem()
    prefix = f"{base}/scenes/".lstrip("/")
    return {name.lstrip("/")[len(prefix):]: hashlib.sha256(fs.cat_file(name)).hexdigest()
            for name in sorted(fs.find(f"{base}/scenes")) if "/.paradrive/" not in name}


# The real stages' smoke profile made tinier still, for the few tests that run the real pipeline:
# 10 frames of 64x48, a 4-iteration fit, two offsets, one clip.
TINY_REAL = {
    "ingest": {"synthetic_frames": 10, "synthetic_width": 64, "synthetic_height": 48},
    "fit": {"checkpoints": [1, 2, 3, 4], "init_points": 500, "sky_points": 100, "eval_views": 1},
    "render": {"condition_checkpoints": [1, 2, 3], "source_checkpoint": 4, "width": 64,
               "height": 48, "offsets_m": [1.0, -1.0], "clips": ["front"]},
}


def tiny_real_sets() -> list[str]:
    """TINY_REAL as command-line arguments: ['--set', 'ingest.synthetic_frames=10', ...]."""
    return [arg for stage, params in TINY_REAL.items() for key, value in params.items()
            for arg in ("--set", f"{stage}.{key}={json.dumps(value)}")]


def run_manifest_with_a_bug(ctx) -> dict:
    """A build-scoped stage with a bug in it (a key its own code expects is not there)."""
    return {"rows": {}["totals"]}
