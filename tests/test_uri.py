"""Scene URIs and the scene ids derived from them."""

import pytest

from paradrive.errors import ConfigError
from paradrive.uri import parse_uri


def test_synthetic_uri_parts_and_id():
    uri = parse_uri("synthetic:demo?seed=7&frames=160")
    assert (uri.kind, uri.path, uri.query) == ("synthetic", "demo", {"seed": "7", "frames": "160"})
    assert uri.scene_id == "synthetic-demo-s7-frames160"


def test_waymo_segment_id_drops_prefix_and_suffix():
    uri = parse_uri("waymo:/logs/segment-1005081002024129653_5313_150_5333_150_with_camera_labels.tfrecord")
    assert uri.scene_id == "waymo-1005081002024129653_5313_150_5333_150"


def test_nuscenes_fragment_and_query_in_either_order():
    a = parse_uri("nuscenes:/data/nuscenes?version=v1.0-trainval#scene-0061")
    b = parse_uri("nuscenes:/data/nuscenes#scene-0061?version=v1.0-trainval")
    assert a.scene == b.scene == "scene-0061"
    assert a.query == b.query == {"version": "v1.0-trainval"}
    assert a.scene_id == "nuscenes-scene-0061"


def test_drivestudio_id_is_a_safe_file_name():
    assert parse_uri("drivestudio:/data/waymo/processed/training/023").scene_id == "drivestudio-023"
    assert "/" not in parse_uri("synthetic:a/b?seed=1").scene_id


@pytest.mark.parametrize("text", ["demo", "kitti:/x", "synthetic:", "synthetic:?seed=1"])
def test_malformed_uri_is_a_clear_error(text):
    with pytest.raises(ConfigError, match="scene URI|path after"):
        parse_uri(text)
