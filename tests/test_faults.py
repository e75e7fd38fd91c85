"""Faults a build meets for real, and what a plain re-run leaves after each.

The fault-injection suite kills a real ``paradrive build`` at a point of every stage: here once
per stage with a fixed seed, ``bench/bench_faults.py`` N times per stage (it imports the functions
of this module). A build runs as a process in a folder of its own
(``data/`` and ``m/`` inside); a point is an event, never a delay. The build stops itself there
(``PARADRIVE_STOP_AT``), is seen stopped and is killed:

- ingest: its k-th camera image written (``ingest:image-<k>``);
- fit: its k-th checkpoint (``fit:checkpoint-<step>``; the fit then resumes from ``gs/state.pt``);
- render: its k-th frame written (``render:frame-<k>``);
- clip: its k-th video encoded (``clip:video-<k>``);
- manifest: a named step of publishing.

After the kill, a plain re-run must exit
0, ``verify_build`` must be clean, no temporary may remain, nothing may appear in the folder
besides ``data/`` and ``m/``, and every output must have the bytes of an uninterrupted build,
except the files whose bytes record when or how long (``NOT_BYTE_STABLE``).
"""

from __future__ import annotations

import contextlib
import fnmatch
import glob
import hashlib
import json
import os
import random
import re
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

import pipeline_stages

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SCENE, SID, BUILD = "synthetic:p1?seed=3", "synthetic-p1-s3", "K"
STAGES = ("ingest", "fit", "render", "clip", "manifest")
# Markers and fit.json hold run ids, times and seconds; the ledger, logs and locks are the
# runner's own; index.json holds its creation time.
NOT_BYTE_STABLE = (".paradrive/*", "*/.paradrive/*", "data/logs/*", "data/locks/*", "m/*/ledger.sqlite*",
                   "m/*/index.json", "*/gs/fit.json")


@dataclass(frozen=True)
class Point:
    """Where a build is killed: in ``stage``, at the step ``stop_at``."""

    stage: str
    stop_at: str

    def describe(self) -> str:
        return f"{self.stage}: {self.stop_at}"


SCENE_DIR = f"data/scenes/{SID}"
# what an uninterrupted build leaves of each stage's steps, and the step's name
WRITTEN = {"ingest": (f"{SCENE_DIR}/images/*/*", "ingest:image"),
           "fit": (f"{SCENE_DIR}/gs/ckpt_*.ply", "fit:checkpoint"),
           "render": (f"{SCENE_DIR}/renders/*/*/*.png", "render:frame"),
           "clip": (f"{SCENE_DIR}/clips/*/*/*.mp4", "clip:video")}
PUBLISH_STEPS = ("publish:first-media", "publish:before-switch")


def points(stage: str, rng: random.Random, reference: Path, n: int) -> list[Point]:
    """``n`` points of ``stage`` drawn with ``rng``: the k-th of the steps the uninterrupted build
    made there (its last one left out: the stage must still be running); a checkpoint by its
    iteration."""
    if stage == "manifest":
        return [Point(stage, rng.choice(PUBLISH_STEPS)) for _ in range(n)]
    pattern, step = WRITTEN[stage]
    files = sorted(glob.glob(str(reference / pattern)))
    if stage == "fit":
        steps = sorted(int(re.findall(r"\d+", Path(f).stem)[-1]) for f in files)
        return [Point(stage, f"{step}-{rng.choice(steps[:-1] or steps)}") for _ in range(n)]
    return [Point(stage, f"{step}-{rng.randint(1, max(1, len(files) - 1))}") for _ in range(n)]


def environment(cache: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PARADRIVE_STAGES", "PARADRIVE_STOP_AT")}
    env.update(PYTHONPATH=str(ROOT), PARADRIVE_CACHE=str(cache), COLUMNS="500")
    return env


def build_command(*extra: str, manifests: str = "m") -> list[str]:
    return [sys.executable, "-m", "paradrive.cli", "build", "--scene", SCENE, "--profile", "smoke",
            *pipeline_stages.tiny_real_sets(), "--data", "data", "--manifests", manifests, "--build",
            BUILD, *extra]


def build(folder: Path, env: dict[str, str], *extra: str) -> subprocess.CompletedProcess:
    folder.mkdir(parents=True, exist_ok=True)
    return subprocess.run(build_command(*extra), cwd=folder, env=env, capture_output=True,
                          text=True)


def kill_at(folder: Path, env: dict[str, str], point: Point) -> bool:
    """Run a build in ``folder`` and SIGKILL it where it stops at ``point``; False when it ended
    without reaching it."""
    folder.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(build_command(), cwd=folder, env={**env, "PARADRIVE_STOP_AT": point.stop_at},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)  # stopped at the step, or ended
        if not os.WIFSTOPPED(status):
            proc.returncode = os.waitstatus_to_exitcode(status)
            return False
        os.killpg(proc.pid, signal.SIGKILL)
        return True
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            proc.wait()


def running_stages(folder: Path) -> list[str]:
    """The stages the ledger of the killed build records as running (where it was killed)."""
    import sqlite3

    path = folder / "m" / BUILD / "ledger.sqlite"
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return [r[0] for r in conn.execute("SELECT stage FROM tasks WHERE state = 'running'")]
    finally:
        conn.close()


def outputs(folder: Path) -> dict[str, str]:
    """sha256 of every file a build left under ``folder``, byte-stable ones only; the published
    version's files by their path inside the version (a re-run may publish another number), the
    versions a publish keeps for readers left out."""
    out: dict[str, str] = {}
    version = _published_version(folder / "m" / BUILD)
    for path in sorted(folder.rglob("*")):
        if not path.is_file() or path.is_symlink():
            continue
        rel = path.relative_to(folder).as_posix()
        if any(fnmatch.fnmatchcase(rel, p) for p in NOT_BYTE_STABLE):
            continue
        if version and rel.startswith(f"m/{BUILD}/{version}/"):
            rel = f"m/{BUILD}/<published>/" + rel.split("/", 3)[3]
        elif fnmatch.fnmatchcase(rel, f"m/{BUILD}/v-*/*"):
            continue   # a version kept for its readers (manifest.keep_versions_for), not the build's
        out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def _published_version(build_dir: Path) -> str:
    try:
        return str(json.loads((build_dir / "index.json").read_text()).get("version") or "")
    except (OSError, ValueError):
        return ""


def temporaries(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if ".tmp-" in p.name)


def healed(folder: Path, env: dict[str, str], reference: dict[str, str],
           rerun: subprocess.CompletedProcess | None = None) -> list[str]:
    """What is wrong after a plain re-run in ``folder`` (empty: healed); ``rerun``: that
    re-run, when the caller made it."""
    from paradrive.inspection import verify_build

    problems = []
    rerun = rerun or build(folder, env)
    if rerun.returncode != 0:
        problems.append(f"re-run exit code {rerun.returncode}: {rerun.stdout[-2000:]}")
    check = verify_build(folder / "m" / BUILD)
    problems += [f"verify: {p}" for p in check["problems"]]
    problems += [f"left behind: {t}" for t in temporaries(folder)]
    problems += [f"outside the data root and build: {p.name}" for p in folder.iterdir()
                 if p.name not in ("data", "m")]
    found = outputs(folder)
    problems += [f"differs from an uninterrupted build: {rel}"
                 for rel in sorted(set(found) | set(reference)) if found.get(rel) != reference.get(rel)]
    return problems


def reference_build(folder: Path, env: dict[str, str]) -> Path:
    """One uninterrupted build in ``folder``: the bytes every healed build must have."""
    done = build(folder, env)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return folder


# -- the suite: a kill in every stage ------------------------------------------------------------

SEED = 20261125


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    return environment(tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, env) -> Path:
    return reference_build(tmp_path_factory.mktemp("reference") / "work", env)


@pytest.mark.parametrize("stage", STAGES)
def test_a_build_killed_in_a_stage_is_healed_by_a_plain_rerun(stage, reference, env, tmp_path):
    """A SIGKILL at a point of ``stage`` drawn from the seed; see the module doc."""
    (point,) = points(stage, random.Random(f"{SEED}-{stage}"), reference, 1)
    folder = tmp_path / "work"
    assert kill_at(folder, env, point), f"the build ended before {point.describe()}"
    assert stage in running_stages(folder), point.describe()  # killed inside the stage
    if stage == "ingest":  # the scene being ingested was left under its temporary name
        assert glob.glob(str(folder / f"data/scenes/.{SID}.tmp-*"))
    assert healed(folder, env, outputs(reference)) == [], point.describe()



def test_two_runs_of_one_build_publish_in_turn(env, tmp_path):
    """Two runs of one build name over other scenes (their scene locks do not meet): the second
    reaches publishing while the first publishes, and waits for it (the first's staging folder
    is not taken for a killed run's); then it publishes its own version. Both exit 0, the build
    verifies and no temporary is left."""
    from paradrive.inspection import verify_build

    folder = tmp_path / "work"
    folder.mkdir()
    first = subprocess.Popen(build_command(), cwd=folder, env={**env, "PARADRIVE_STOP_AT": "publish:first-media"},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    second = None
    try:
        _, status = os.waitpid(first.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), "the first run ended before it published"
        staging = glob.glob(str(folder / f"m/{BUILD}/.v-*.tmp-*"))
        assert staging, "the first run holds no staging folder"
        other = [a.replace(SCENE, "synthetic:p1?seed=4") for a in build_command()]
        second = subprocess.Popen(other, cwd=folder, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        seen = []
        assert second.stdout is not None
        for line in second.stdout:   # it says it waits, and waits
            seen.append(line)
            if "is being published by another run; waiting" in line:
                break
        assert second.poll() is None, "".join(seen)[-3000:]
        assert all(Path(s).is_dir() for s in staging)   # the first run's staging is still there
        os.kill(first.pid, signal.SIGCONT)
        assert first.wait() == 0
        rest = second.communicate()[0]
        assert second.returncode == 0, ("".join(seen) + rest)[-3000:]
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    check = verify_build(folder / "m" / BUILD)
    assert check["ok"], check["problems"]
    assert temporaries(folder) == []
