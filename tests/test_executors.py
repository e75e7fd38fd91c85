"""What every executor shares (paradrive/pipeline/executors/base.py): the options of a run, one
result per (scene, stage) asked with a failed stage's later ones recorded blocked, and the part
of the options a task takes to another process."""

from __future__ import annotations

import pickle

from paradrive.pipeline.executors import RunOptions, SceneTask
from paradrive.pipeline.executors.base import Completion
from paradrive.pipeline.locks import LockOptions
from paradrive.pipeline.runner import StageResult


def test_a_failed_stage_records_the_scenes_later_stages_blocked_in_order():
    seen: list[tuple[str, str]] = []
    done = Completion(lambda r: seen.append((r.stage, r.status)))
    task = SceneTask("synthetic:demo?seed=7", ("ingest", "fit", "render", "clip"))
    assert done.stage_done(task, 0, StageResult("s7", "ingest", "done"))
    assert not done.stage_done(task, 1, StageResult("s7", "fit", "failed", error="bad pose"))
    assert seen == [("ingest", "done"), ("fit", "failed"), ("render", "blocked"), ("clip", "blocked")]
    assert [r.error for r in done.results[2:]] == ["not run: fit failed"] * 2
    last = Completion()
    assert not last.stage_done(SceneTask("u", ("ingest",)), 0, StageResult("s", "ingest", "done"))


def test_a_worker_takes_the_options_without_the_drivers_callbacks():
    options = RunOptions(force=True, on_start=lambda uri, stage: None, on_result=lambda r: None,
                         locks=LockOptions("b", 5.0), on_progress=lambda snap: None, verify_outputs=True)
    shipped = pickle.loads(pickle.dumps(options.for_worker()))   # as Ray sends a task's arguments
    assert shipped == RunOptions(force=True, locks=LockOptions("b", 5.0), verify_outputs=True)
