"""Tables printed to a pipe are read by scripts: no name or value in them is cut to fit a width
(``paradrive stages | grep max_dynamic_fraction`` finds it), whatever the names' lengths."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from paradrive.pipeline import StageRegistry

REPO = Path(__file__).resolve().parents[1]


def piped(*args: str) -> str:
    """stdout of ``paradrive ARGS`` through a pipe, with no COLUMNS in the environment."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    done = subprocess.run([sys.executable, "-m", "paradrive.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_every_parameter_of_every_stage_is_whole_on_its_line_through_a_pipe():
    text = piped("stages")
    registry = StageRegistry()
    for name in registry.order(None):
        for key, param in registry.specs[name].params.items():
            rows = [ln for ln in text.splitlines() if ln.startswith(f"│ {key} ")]
            # the whole row on one line: the name, and its doc to the last word
            assert any(param.doc.split()[-1] in row for row in rows), (name, key)


def test_a_long_scene_id_and_its_reason_are_whole_in_status_through_a_pipe(tmp_path):
    from paradrive.pipeline.ledger import Ledger
    from paradrive.pipeline.runner import StageResult

    name = "a-street-with-a-long-name-that-a-table-at-eighty-columns-would-cut"
    uri, sid = f"synthetic:{name}?seed=1", f"synthetic-{name}-s1"
    ledger = Ledger.for_build(tmp_path, "b")
    ledger.register([uri], ["ingest"])
    reason = f"scene {sid}: ingest failed: a reason long enough to be folded at eighty columns"
    ledger.record(StageResult(sid, "ingest", "failed", seconds=1.5, error=reason))
    ledger.close()
    text = piped("status", "b", "--manifests", str(tmp_path))
    assert any(sid in line and line.rstrip().endswith(reason[-30:]) for line in text.splitlines()), text
