"""Declarative stages: the runner reads stages/*.yaml and profiles; typos are errors, never defaults."""

import shutil

import pytest
import yaml

from paradrive.errors import ConfigError
from paradrive.pipeline import StageRegistry, parse_overrides
from paradrive.contracts.specs import default_stages_dir


def test_paper_defaults_live_in_the_stage_files():
    config = StageRegistry().resolve(None)
    render = config.params["render"]
    assert render["condition_checkpoints"] == [100, 500, 1000]
    assert render["source_checkpoint"] == 30000
    assert sorted(render["offsets_m"]) == [-4.0, -3.0, -2.0, -1.0, 1.0, 2.0, 3.0, 4.0]
    assert render["clips"] == ["front", "middle", "rear"] and render["clip_frames"] == 121
    assert (render["height"], render["width"]) == (480, 832)
    assert config.params["fit"]["checkpoints"][-1] == 30000


def test_stages_resolve_in_dependency_order():
    registry = StageRegistry()
    assert registry.order() == ["ingest", "fit", "render", "clip", "manifest", "encode"]
    # encode runs only when asked for (enabled_by: vae): a default build stops at the manifest
    config = registry.resolve(None, {})
    assert config.selected() == ["ingest", "fit", "render", "clip", "manifest"]
    assert config.selected(["manifest", "encode"]) == ["manifest", "encode"]
    assert registry.order(["clip", "ingest"]) == ["ingest", "clip"]


def test_profile_overrides_and_records_where_values_come_from():
    config = StageRegistry().resolve("smoke", parse_overrides(["render.width=64"]))
    assert config.params["ingest"]["synthetic_frames"] < 121
    assert config.origins["ingest"]["synthetic_frames"] == "profile smoke"
    assert config.params["render"]["width"] == 64
    assert config.origins["render"]["width"] == "command line"
    assert config.origins["render"]["offsets_m"] == "default"


def test_typo_in_override_is_an_error_with_a_suggestion():
    with pytest.raises(ConfigError, match="no parameter 'widht'.*did you mean 'width'"):
        StageRegistry().resolve(None, {"render": {"widht": 3}})


def test_wrong_type_in_override_is_an_error():
    with pytest.raises(ConfigError, match="render.width = 'wide' has type str, expected int"):
        StageRegistry().resolve(None, parse_overrides(["render.width=wide"]))


def test_unknown_profile_lists_the_profiles():
    with pytest.raises(ConfigError, match="unknown profile 'smok'.*did you mean 'smoke'"):
        StageRegistry().resolve("smok")


@pytest.fixture
def stages_copy(tmp_path):
    dst = tmp_path / "stages"
    shutil.copytree(default_stages_dir(), dst)
    return dst


def test_typo_in_a_stage_file_is_an_error(stages_copy):
    doc = yaml.safe_load((stages_copy / "clip.yaml").read_text())
    doc["resorces"] = doc.pop("resources")
    (stages_copy / "clip.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r"clip.yaml: unknown key 'resorces'"):
        StageRegistry(stages_copy).specs


def test_param_without_doc_is_an_error(stages_copy):
    doc = yaml.safe_load((stages_copy / "clip.yaml").read_text())
    doc["params"]["crf"] = {"default": 18}
    (stages_copy / "clip.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r"params.crf.doc"):
        StageRegistry(stages_copy).specs


def test_unknown_need_is_an_error(stages_copy):
    doc = yaml.safe_load((stages_copy / "clip.yaml").read_text())
    doc["needs"] = ["rendr"]
    (stages_copy / "clip.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="needs unknown stage 'rendr'.*did you mean 'render'"):
        StageRegistry(stages_copy).specs


def test_dependency_cycle_is_an_error(stages_copy):
    doc = yaml.safe_load((stages_copy / "ingest.yaml").read_text())
    doc["needs"] = ["clip"]
    (stages_copy / "ingest.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match="cycle"):
        StageRegistry(stages_copy).specs
