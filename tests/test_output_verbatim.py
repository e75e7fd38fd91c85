"""What the terminal shows of user data is the data: square brackets in an error, a YAML value or
a parameter's doc are printed as they are, not taken for console markup and dropped."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# a wide terminal: the tables keep each value on one line
ENV = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "1000"}


def _paradrive(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "paradrive.cli", *map(str, args)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def failed_ingest(tmp_path_factory):
    """A build whose only scene fails ingest with a fix that holds a bracketed list."""
    root = tmp_path_factory.mktemp("verbatim")
    done = _paradrive("build", "--scene", "synthetic:demo?seed=7", "--profile", "smoke",
                      "--set", "ingest.cameras=[nosuch]", "--stages", "ingest", "--data", root / "data",
                      "--manifests", root / "manifests", "--build", "v")
    (log,) = (root / "data" / "logs").glob("*.log")
    return {"run": done, "log": log.read_text(), "manifests": root / "manifests"}


def _suggestion(text: str) -> str:
    found = re.findall(r"--set ingest\.cameras=\[[^\]\s]*\]", " ".join(text.split()))
    assert found, text
    return found[0].removeprefix("--set ")


def test_a_failed_scene_prints_its_bracketed_fix_as_the_log_holds_it(failed_ingest):
    run = failed_ingest["run"]
    assert run.returncode == 1, run.stdout + run.stderr
    fix = _suggestion(failed_ingest["log"])
    assert fix.startswith("ingest.cameras=[front")
    assert fix in run.stderr   # the failed stage's line as it happens
    assert fix in run.stdout   # the build summary's reason column


def test_status_prints_the_bracketed_reason(failed_ingest):
    status = _paradrive("status", "v", "--manifests", failed_ingest["manifests"])
    assert status.returncode == 0, status.stderr
    assert _suggestion(failed_ingest["log"]) in status.stdout


def test_the_stages_table_prints_a_doc_with_brackets_as_written():
    import yaml

    doc = yaml.safe_load((REPO / "stages" / "manifest.yaml").read_text())["params"]["exclude_splits"]["doc"]
    assert "[none]" in doc
    shown = _paradrive("stages", "manifest")
    assert shown.returncode == 0, shown.stderr
    assert doc in " ".join(shown.stdout.split())
