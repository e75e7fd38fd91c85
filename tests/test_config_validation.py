"""The whole configuration is checked before any stage runs: each parameter's range or choices
live in its stage file, and a value outside them (from the defaults, a profile or --set) is a
one-line error naming the parameter, the value, what is allowed and where the value came from;
exit code 2, and nothing is written."""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from paradrive.errors import EXIT_USAGE, ConfigError
from paradrive.pipeline import StageRegistry, parse_overrides
from paradrive.contracts.specs import default_stages_dir

REPO = Path(__file__).resolve().parents[1]
SCENE = "synthetic:p1?seed=3"


def _build(tmp_path: Path, *args: str, stages_dir: Path | None = None) -> subprocess.CompletedProcess:
    """``paradrive build`` of one smoke scene into ``tmp_path/work`` (a real process)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "100"}
    if stages_dir is not None:
        env["PARADRIVE_STAGES"] = str(stages_dir)
    work = tmp_path / "work"
    return subprocess.run([sys.executable, "-m", "paradrive.cli", "build", "--scene", SCENE,
                           "--data", str(work / "data"), "--manifests", str(work / "m"),
                           "--build", "K", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)


def _refused(res: subprocess.CompletedProcess, tmp_path: Path) -> str:
    """The one line a refused build printed; nothing was written."""
    assert res.returncode == EXIT_USAGE, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert not (tmp_path / "work").exists()
    return lines[0]


@pytest.mark.parametrize(("override", "allowed"), [
    ("fit.downscale=0", "at least 1"),
    ("fit.checkpoints=[]", "not empty"),
    ("fit.sh_degree=99", "at least 0, at most 3"),
    ("fit.device=tpu", "matching auto|cpu|cuda"),
    ("fit.lr_means=.nan", "more than 0"),
    ("fit.threads=-5", "at least 0"),
    ("clip.crf=999", "at least 0, at most 51"),
])
def test_a_value_out_of_its_range_stops_the_build_before_any_stage(tmp_path, override, allowed):
    line = _refused(_build(tmp_path, "--profile", "smoke", "--set", override), tmp_path)
    name, _, raw = override.partition("=")
    value = repr(yaml.safe_load(raw))
    assert line.startswith(f"error: --set: {name} = {value} "), line
    assert f"allowed: {allowed}" in line and "change it to an allowed value" in line


def test_a_profile_value_out_of_range_names_the_profile_file(tmp_path):
    stages = tmp_path / "stages"
    shutil.copytree(default_stages_dir(), stages)
    (stages / "profiles" / "bad.yaml").write_text("name: bad\nstages:\n  fit: {threads: -5}\n")
    line = _refused(_build(tmp_path, "--profile", "bad", stages_dir=stages), tmp_path)
    assert line.startswith(f"error: profile bad ({stages / 'profiles' / 'bad.yaml'}): "
                           f"fit.threads = -5 is out of range (allowed: at least 0)"), line


def test_a_profile_of_random_bytes_is_one_line_naming_the_file(tmp_path):
    stages = tmp_path / "stages"
    shutil.copytree(default_stages_dir(), stages)
    profile = stages / "profiles" / "noise.yaml"
    profile.write_bytes(b"name: x\n\x92\xff\x00 binary")
    line = _refused(_build(tmp_path, "--profile", "noise", stages_dir=stages), tmp_path)
    assert line == (f"error: {profile}: not a text file (byte 0x92 at offset 8 is not UTF-8); "
                    f"give a YAML file")


def test_a_yaml_error_is_one_line_with_file_line_and_column(tmp_path):
    stages = tmp_path / "stages"
    shutil.copytree(default_stages_dir(), stages)
    profile = stages / "profiles" / "broken.yaml"
    profile.write_text("name: broken\nstages:\n  fit: {threads: [1\n  render: {width: 64}\n")
    line = _refused(_build(tmp_path, "--profile", "broken", stages_dir=stages), tmp_path)
    assert line.startswith(f"error: {profile}:4:9: not valid YAML: "), line
    assert line.endswith("; fix the YAML there")


def test_a_render_checkpoint_the_fit_does_not_write_is_refused_naming_both(tmp_path):
    line = _refused(_build(tmp_path, "--profile", "smoke", "--set", "render.source_checkpoint=200"),
                    tmp_path)
    assert line == ("error: render.source_checkpoint = 200 is not among fit.checkpoints = "
                    "[25, 50, 100, 300] (values from: command line, profile smoke); add 200 to "
                    "fit.checkpoints or change render.source_checkpoint")


def test_a_repeated_offset_is_refused_before_ingest_not_by_render_after_the_fit(tmp_path):
    line = _refused(_build(tmp_path, "--profile", "smoke", "--set", "render.offsets_m=[1,1]"),
                    tmp_path)
    assert line == ("error: render.offsets_m: repeats the offset +1m; list each offset once "
                    "(got [1, 1]) (from --set)")


@pytest.mark.parametrize(("key", "values", "words"), [
    ("offsets_m", [2, -1, 2.0], "the offset +2m"),
    ("longitudinal_offsets_m", [0.5, 0.50], "the offset +0.5m"),
    ("condition_checkpoints", [25, 50, 25], "the checkpoint 25"),
    ("clips", ["front", "rear", "front"], "the clip front"),
    ("cameras", ["front", "front"], "the camera front"),
])
def test_every_repeat_render_would_meet_is_refused_with_the_configuration(key, values, words):
    config = StageRegistry().resolve("smoke", {"render": {key: values}})
    with pytest.raises(ConfigError, match=rf"^render\.{key}: repeats {re.escape(words)}; list each "):
        config.check()


def test_a_value_the_rules_let_through_but_the_stage_cannot_take_names_its_source():
    config = StageRegistry().resolve("smoke", parse_overrides(["fit.cameras=[1, 2]"]))
    with pytest.raises(ConfigError, match=r"^fit\.cameras\.0: .*string.* \(from --set\)$"):
        config.check(["fit"])
    config.check(["ingest"])   # a stage not selected is not held to it


def _params(kind: type) -> list[tuple[str, str]]:
    registry = StageRegistry()
    return [(stage, key) for stage, spec in registry.specs.items()
            for key, param in spec.params.items() if type(param.default) is kind]


@pytest.mark.parametrize(("stage", "key"), _params(float))
def test_nan_and_infinity_are_refused_for_every_float(stage, key):
    for value in (math.nan, math.inf):
        with pytest.raises(ConfigError, match=rf"--set: {stage}\.{key} = {value} is not a finite number"):
            StageRegistry().resolve(None, {stage: {key: value}})


def test_nan_inside_a_list_is_refused():
    with pytest.raises(ConfigError, match=r"render.offsets_m = \[1.0, nan\] has an element nan that "
                                          r"is not a finite number"):
        StageRegistry().resolve(None, parse_overrides(["render.offsets_m=[1.0, .nan]"]))


def test_every_number_and_word_parameter_declares_what_it_may_be():
    undeclared = [f"{stage}.{key}" for stage, spec in StageRegistry().specs.items()
                  for key, p in spec.params.items()
                  if (isinstance(p.default, (int, float)) and not isinstance(p.default, bool)
                      and p.min is None and p.max is None and p.above is None and p.below is None
                      and key != "synthetic_curvature")   # any finite curvature is a street
                  or (isinstance(p.default, str) and p.choices is None and p.pattern is None
                      and p.types is None)]
    assert undeclared == []


def test_a_default_outside_its_own_range_is_an_error_naming_the_stage_file(tmp_path):
    stages = tmp_path / "stages"
    shutil.copytree(default_stages_dir(), stages)
    doc = yaml.safe_load((stages / "clip.yaml").read_text())
    doc["params"]["crf"]["default"] = 60
    (stages / "clip.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=rf"{stages / 'clip.yaml'}: clip.crf default 60 is out of range"):
        StageRegistry(stages).specs


def test_null_is_refused_unless_the_parameter_takes_it():
    with pytest.raises(ConfigError, match=r"--set: fit.downscale = null is not allowed"):
        StageRegistry().resolve(None, parse_overrides(["fit.downscale=null"]))
    config = StageRegistry().resolve(None, parse_overrides(["fit.init_ground_margin=null",
                                                            "ingest.cameras=null"]))
    assert config.params["fit"]["init_ground_margin"] is None
    config.check()


def test_the_profiles_and_defaults_pass_their_own_rules():
    for profile in [None, *StageRegistry().profiles()]:
        StageRegistry().resolve(profile).check()


def test_paradrive_stages_shows_what_each_parameter_may_be(monkeypatch):
    """The table a user reads before a --set names the same rules the validation enforces."""
    from typer.testing import CliRunner

    from paradrive import cli
    from paradrive.commands import common

    monkeypatch.setattr(common.out, "width", 250)  # one table row a line, whatever the terminal
    result = CliRunner().invoke(cli.app, ["stages", "manifest"])
    assert result.exit_code == 0, result.output
    spec = StageRegistry().specs["manifest"]
    rows = {line.split("│")[1].strip(): line for line in result.output.splitlines() if line.count("│") > 4}
    assert "allowed" in result.output
    assert spec.params["compression"].allowed() in rows["compression"]
    assert "at least 1, or null" in rows["shard_bytes"]


def _train_settings(tree, where=""):
    from paradrive.contracts.specs import Param

    for key, node in tree.items():
        if isinstance(node, Param):
            yield f"{where}{key}", node
        else:
            yield from _train_settings(node, f"{where}{key}.")


def test_every_training_setting_declares_what_it_may_be_and_is_held_to_it():
    from paradrive.train.trainer import CONFIG_DIR, _load, load_config

    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        params, _ = _load(path)
        undeclared = [key for key, p in _train_settings(params)
                      if (isinstance(p.default, (int, float)) and not isinstance(p.default, bool)
                          and p.min is None and p.max is None and p.above is None and p.below is None)
                      or (isinstance(p.default, str) and p.choices is None and p.pattern is None
                          and key != "train.stage1_trainable")]   # 'all' or a list of module names
        assert undeclared == [], path.name
    with pytest.raises(ConfigError, match=r"train.lr = -1.0 is out of range \(allowed: more than 0\)"):
        load_config("smoke", {"train": {"lr": -1}})


def test_exponent_numbers_without_a_dot_are_floats_in_every_set():
    """YAML 1.1 reads 1e-3 as a string: a learning rate given so reached the trainer as text."""
    from paradrive.train.trainer import parse_set

    assert parse_overrides(["fit.lr=3E-4", "render.offsets_m=[1e0, -2]"]) == {
        "fit": {"lr": 3e-4}, "render": {"offsets_m": [1.0, -2]}}
    assert parse_set(["train.lr=1e30", "train.name='1e3'", "train.n=12"]) == {
        "train": {"lr": 1e30, "name": "1e3", "n": 12}}
    assert isinstance(parse_set(["train.n=12"])["train"]["n"], int)
