"""Secrets are masked by name at any depth (mappings, JSON values, URL queries, ``user:pass@``)
in everything a build writes: the ledger's command and errors, scene logs, markers, index.json
and what it prints."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import pipeline_stages
from paradrive.redact import MASK, redact, redact_argv, redact_options, remember, secret_values

REPO = Path(__file__).resolve().parents[1]
NESTED = "NESTEDSECRET8"
QUERY = "QUERYSECRET9"


def test_a_secret_inside_a_json_option_is_masked_in_the_recorded_command():
    option = json.dumps({"region_name": "us-east-1", "aws_secret_access_key": NESTED})
    recorded = " ".join(redact_argv(["paradrive", "build", "--storage-option", f"client_kwargs={option}",
                                     f"--storage-option=endpoint_url=http://h:9/?X-Amz-Security-Token={QUERY}&v=2",
                                     "--set", f"ingest.cameras=[{NESTED}]"]))
    assert NESTED not in recorded and QUERY not in recorded
    # what is not secret still says what ran
    assert '"region_name":"us-east-1"' in recorded and '"aws_secret_access_key":"***"' in recorded
    assert "endpoint_url=http://h:9/?X-Amz-Security-Token=***&v=2" in recorded


def test_free_text_loses_secrets_found_by_name_at_any_depth():
    text = (f'retry with {{"client_kwargs": {{"aws_session_token": "{NESTED}"}}}} at '
            f"https://user:{QUERY}@minio:9000/b?token={QUERY}-2&part=1")
    shown = redact(text)
    assert NESTED not in shown and QUERY not in shown
    assert '"aws_session_token": "***"' in shown and "https://***@minio:9000/b?token=***&part=1" in shown
    # a value found by name in the options is masked wherever it turns up
    options = {"client_kwargs": json.dumps({"config": {"aws_secret_access_key": NESTED}})}
    assert NESTED in secret_values(options)
    assert redact(f"signature of {NESTED} does not match", options) == f"signature of {MASK} does not match"
    assert redact_options({"client_kwargs": {"config": {"secret_key": NESTED, "region": "eu"}}}) == \
        {"client_kwargs": {"config": {"secret_key": MASK, "region": "eu"}}}


def test_remembered_options_are_masked_where_the_writer_does_not_have_them():
    remember({"client_kwargs": {"aws_secret_access_key": f"{NESTED}-remembered"}})
    assert redact(f"ledger error: denied for {NESTED}-remembered") == f"ledger error: denied for {MASK}"


def _files_holding(text: str, *folders: Path) -> list[str]:
    return [str(p) for folder in folders for p in folder.rglob("*")
            if p.is_file() and text.encode() in p.read_bytes()]


@pytest.mark.slow
def test_a_build_with_a_nested_secret_writes_it_nowhere(s3_bucket, tmp_path):
    from paradrive.pipeline.ledger import Ledger
    from paradrive.storage import DataRoot

    # the credentials only inside client_kwargs (s3fs passes key / secret there itself)
    client = {**s3_bucket["client_kwargs"], "aws_access_key_id": s3_bucket["key"],
              "aws_secret_access_key": NESTED}
    options = {"endpoint_url": s3_bucket["endpoint_url"], "client_kwargs": client}
    flags = [arg for name, value in options.items()
             for arg in ("--storage-option", f"{name}={json.dumps(value)}")]
    url = "s3://builds/nested-secret"
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "250",
           "PARADRIVE_CACHE": str(tmp_path / "cache")}
    res = subprocess.run([sys.executable, "-m", "paradrive.cli", "build", "--scene", "synthetic:demo?seed=2",
                          "--profile", "smoke", *pipeline_stages.tiny_real_sets(), "--data", url, *flags,
                          "--manifests", str(tmp_path / "manifests"), "--build", "b"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]

    remote = DataRoot.of(url, storage_options=s3_bucket)
    fs, base = remote.filesystem()
    stored = fs.find(base)
    build = tmp_path / "manifests" / "b"
    # what is searched holds the ledger, the scene log, the markers and the index
    assert (build / "ledger.sqlite").is_file() and (build / "index.json").is_file()
    assert any(name.endswith(".log") for name in stored)
    assert any("/.paradrive/" in name and name.endswith(".json") for name in stored)
    assert [name for name in stored if NESTED.encode() in fs.cat_file(name)] == []
    assert _files_holding(NESTED, tmp_path / "cache", tmp_path / "manifests") == []
    assert NESTED not in res.stdout + res.stderr
    (run,) = Ledger.for_build(tmp_path / "manifests", "b").runs()
    assert '"aws_secret_access_key":"***"' in run["command"], run["command"]
