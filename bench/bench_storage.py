"""A URL data root's cost: uploading and downloading a scene folder, against a plain copy; prints JSON.

    .venv/bin/python bench/bench_storage.py [--files 1200] [--kb 64]

A scene-shaped folder (``--files`` files of ``--kb`` KB under images/, renders/… and a few JSON
markers) is pushed to a root and pulled back into an empty cache, as a stage on a fresh node
would. Two fsspec filesystems run here without a network: ``memory://`` (whole-object writes,
like S3) and ``local://`` (a folder reached through fsspec: every upload goes through a
temporary name and a rename). The baseline is ``shutil.copytree`` of the same folder in the
same run. A real object store adds its network time on top; the ratio is the bookkeeping.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def make_scene(folder: Path, files: int, kb: int) -> int:
    """``files`` files spread like a scene's (images, renders of 11 streams, checkpoints)."""
    rng = os.urandom(kb * 1024)
    total = 0
    for i in range(files):
        kind = ("images", "renders/source_+1m", "renders/cond_000100", "depth")[i % 4]
        path = folder / kind / f"{i:06d}.bin"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(rng[i % 97:] + rng[:i % 97])
        total += kb * 1024
    (folder / ".paradrive").mkdir()
    (folder / ".paradrive" / "render.json").write_text("{}")
    return total


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def bench(url: str, source: Path, work: Path) -> dict:
    from paradrive.storage import DataRoot, SceneMirror

    root = DataRoot.of(url, cache_dir=str(work / f"cache-{uuid.uuid4().hex[:6]}"))
    mirror = SceneMirror(root, "scene")
    shutil.copytree(source, mirror.local)  # the stage wrote its files into the cache
    before: dict = {}
    push = timed(lambda: mirror.push(before, last=[".paradrive/render.json"]))
    shutil.rmtree(root.local)  # a fresh node
    fresh = SceneMirror(root, "scene")
    pull = timed(lambda: (fresh.refresh(), fresh.pull()))
    skip = timed(lambda: (fresh.refresh(), fresh.pull([".paradrive/*.json"], prune=True)))
    return {"url": url.split("://")[0] + "://", "push_s": round(push, 3), "pull_s": round(pull, 3),
            "up_to_date_check_s": round(skip, 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=1200)
    ap.add_argument("--kb", type=int, default=64)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        source = work / "scene"
        size = make_scene(source, args.files, args.kb)
        copy = timed(lambda: shutil.copytree(source, work / "copy"))
        results = [bench(f"memory://bench-{uuid.uuid4().hex[:6]}/run", source, work),
                   bench(f"local://{work / 'remote'}", source, work)]
    for r in results:
        r["push_vs_copytree"] = round(r["push_s"] / copy, 2)
        r["pull_vs_copytree"] = round(r["pull_s"] / copy, 2)
    print(json.dumps({"bench": "storage", "files": args.files + 1, "mb": round(size / 2**20, 1),
                      "copytree_s": round(copy, 3), "roots": results,
                      "machine": {"cpus": os.cpu_count(), "python": platform.python_version()}},
                     indent=2))


if __name__ == "__main__":
    main()
