"""The ingest parameters a scene was made with, as later stages and eval read them back: what an
older marker lacks comes from the build's own parameters (its profile and ``--set``), not from
the stage file's defaults, and the stage file is not read again on every call."""

from __future__ import annotations

from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import StageMarker
from paradrive.contracts import specs
from paradrive.pipeline import StageRegistry
from paradrive.contracts.params import params_of, recorded_params


def _old_marker(tmp_path, dropped: tuple[str, ...]) -> SceneLayout:
    """A scene whose ingest marker an older version wrote, before the ``dropped`` keys existed."""
    layout = SceneLayout(tmp_path / "scenes" / "synthetic-demo-s7")
    values = StageRegistry().resolve("smoke").params["ingest"]
    StageMarker(stage="ingest", scene_id="synthetic-demo-s7", scene_uri="synthetic:demo?seed=7",
                fingerprint="old", params={k: v for k, v in values.items() if k not in dropped},
                ).save(layout.marker("ingest"))
    return layout


def test_an_old_markers_gaps_come_from_the_builds_parameters(tmp_path):
    layout = _old_marker(tmp_path, ("synthetic_frames", "moving_threshold_m"))
    build = StageRegistry().resolve("smoke", {"ingest": {"moving_threshold_m": 0.7}}).params["ingest"]
    params = recorded_params(layout, build)
    assert params.synthetic_frames == 24 and params.moving_threshold_m == 0.7   # the build's
    assert params.synthetic_width == 160                                     # the marker's own
    paper = StageRegistry().resolve(None).params["ingest"]
    bare = recorded_params(layout)   # no build at hand: the stage file's defaults
    assert bare.synthetic_frames == paper["synthetic_frames"]
    assert bare.moving_threshold_m == paper["moving_threshold_m"]


def test_the_stage_file_is_read_once_not_on_every_call(monkeypatch):
    reads = []
    read = specs._read_yaml
    monkeypatch.setattr(specs, "_read_yaml", lambda path: reads.append(path) or read(path))
    params_of({"image_ext": "png"})
    first = len(reads)
    for _ in range(5):
        assert params_of({"image_ext": "png"}).image_ext == "png"
    assert len(reads) == first
