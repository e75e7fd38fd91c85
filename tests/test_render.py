"""The render stage: clip frames only, recorded / under-fitted / shifted streams, intrinsics, depth EXR."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import stage_params

from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.pipeline import StageRegistry, run_build
from paradrive.streams import crop_resize, output_camera
from paradrive.gs.views import render_views
from paradrive.exr import read_depth_exr, write_depth_exr
from paradrive.stages.render import render_scene
from paradrive.scene import load_scene, read_image

SCENE = "synthetic:demo?seed=7"
SID = "synthetic-demo-s7"



def fitted_model(scene_dir, iteration: int):
    """The checkpoint as the render stage loads it (background plus actor nodes)."""
    from paradrive.gs.graph import load_model
    from paradrive.contracts.layout import SceneLayout
    from paradrive.contracts.records import FitRecord

    layout = SceneLayout(scene_dir)
    return load_model(layout, iteration, load_scene(scene_dir), FitRecord.load(layout.fit_json))

def smoke_params(**render) -> dict:
    """Resolved smoke parameters (the smoke profile must render checkpoints its fit writes)."""
    config = StageRegistry().resolve("smoke", {"render": render} if render else None)
    fit, rp = config.params["fit"], config.params["render"]
    needed = set(rp["condition_checkpoints"]) | {rp["source_checkpoint"]}
    assert needed <= set(fit["checkpoints"]), (
        f"stages/profiles/smoke.yaml renders checkpoints {sorted(needed)} that fit.checkpoints "
        f"{fit['checkpoints']} does not write")
    return config


@pytest.fixture(scope="module")
def rendered(request, tmp_path_factory):
    """The smoke scene rendered for its middle clip, with depth and alpha and offsets 0 and +2 m."""
    config = smoke_params(clips=["middle"], offsets_m=[0.0, 2.0], depth=True, alpha=True)
    smoke = request.getfixturevalue("smoke_scene")
    root = tmp_path_factory.mktemp("rendered")
    shutil.copytree(smoke["data_dir"], root / "data")
    report = run_build(config, [SCENE], root / "data", stages=["render"])
    assert not report.failures(), report.failures()[0].error
    scene_dir = root / "data" / "scenes" / SID
    doc = json.loads((scene_dir / "renders" / "renders.json").read_text())
    return {"dir": scene_dir, "doc": doc, "params": config.params["render"],
            "ingest": config.typed("ingest")}


# --------------------------------------------------------------------------- intrinsics (pure)

def test_output_camera_centre_crops_to_the_output_aspect_then_scales():
    out = output_camera(200, 100, 100.0, 90.0, 101.0, 49.0, 80, 50)   # stored 2:1, output 8:5
    assert out.crop == (20, 0, 160, 100)
    fx, fy, cx, cy = out.intrinsics
    assert (fx, fy) == pytest.approx((50.0, 45.0))
    assert (cx, cy) == pytest.approx(((101.0 - 20) * 0.5, 49.0 * 0.5))
    tall = output_camera(100, 200, 100.0, 100.0, 50.0, 100.0, 100, 100)
    assert tall.crop == (0, 50, 100, 100)
    assert tall.intrinsics[3] == pytest.approx(50.0)


def test_crop_resize_moves_a_pixel_where_the_intrinsics_say():
    stored = np.zeros((100, 200, 3), np.uint8)
    K = np.array([[100.0, 0, 101.0], [0, 90.0, 49.0], [0, 0, 1]])
    point = np.array([[0.7, -0.3, 5.0]])
    uv, _ = geometry.project(point, np.eye(4), K)
    u, v = np.floor(uv[0]).astype(int)
    stored[v - 1:v + 1, u - 1:u + 1] = 255          # a 2x2 blob around the projected point
    out = output_camera(200, 100, 100.0, 90.0, 101.0, 49.0, 80, 50)
    small = crop_resize(stored, out)
    assert small.shape == (50, 80, 3)
    uv2, _ = geometry.project(point, np.eye(4), out.K)
    ys, xs = np.nonzero(small[..., 0] > 0)
    weights = small[ys, xs, 0].astype(float)
    centre = np.array([np.average(xs, weights=weights), np.average(ys, weights=weights)]) + 0.5
    assert np.allclose(centre, uv2[0], atol=0.35)


# --------------------------------------------------------------------------- depth files

def test_depth_exr_round_trips_float32_including_infinity(tmp_path):
    import OpenEXR

    depth = np.linspace(0.5, 80.0, 12 * 7, dtype=np.float32).reshape(7, 12)
    depth[0, 0] = np.inf
    write_depth_exr(tmp_path / "d.exr", depth)
    with OpenEXR.File(str(tmp_path / "d.exr")) as f:
        z = f.channels()["Z"].pixels
    assert z.dtype == np.float32 and np.array_equal(z, depth)
    assert np.array_equal(read_depth_exr(tmp_path / "d.exr"), depth)
    assert [p.name for p in tmp_path.iterdir()] == ["d.exr"]


# --------------------------------------------------------------------------- the stage

def test_renders_only_the_frames_of_the_clip_windows(rendered):
    doc, p = rendered["doc"], rendered["params"]
    cam = doc["cameras"]["front"]
    n, f = 24, p["clip_frames"]
    start = (n - f) // 2
    assert cam["windows"] == [{"clip": "middle", "frame_start": start, "num_frames": f}]
    assert cam["frames"] == list(range(start, start + f))
    names = ["target"] + [f"cond@{i:06d}" for i in p["condition_checkpoints"]] + ["source+0m", "source+2m"]
    assert list(cam["streams"]) == names
    for name in names:
        folder = rendered["dir"] / "renders" / "front" / name
        assert sorted(x.name for x in folder.glob("*.png")) == [f"{i:06d}.png" for i in cam["frames"]]
    assert doc["condition_checkpoints"] == p["condition_checkpoints"]
    assert doc["source_checkpoint"] == p["source_checkpoint"]


def test_target_stream_is_the_recorded_frames_at_output_size(rendered):
    scene = load_scene(rendered["dir"])
    cam = rendered["doc"]["cameras"]["front"]
    for pos in cam["frames"][:3]:
        png = read_image(rendered["dir"] / "renders" / "front" / "target" / f"{pos:06d}.png")
        assert png.shape == (96, 160, 3)
        assert np.array_equal(png, scene.load_image(pos, "front"))   # same size: an exact copy
    c = scene.cameras["front"]
    assert cam["intrinsics"] == pytest.approx([c.fx, c.fy, c.cx, c.cy])


def test_source_streams_follow_the_lateral_shift_and_conditions_the_recorded_trajectory(rendered):
    scene = load_scene(rendered["dir"])
    cam = rendered["doc"]["cameras"]["front"]
    frames = cam["frames"]
    recorded = scene.c2w("front")[frames]
    ego = scene.ego2world()[frames]
    streams = cam["streams"]
    shifted = geometry.as_pose(streams["source+2m"]["c2w"])
    assert np.allclose(shifted, geometry.lateral_shift(recorded, ego, 2.0))
    assert np.allclose(np.linalg.norm(shifted[:, :3, 3] - recorded[:, :3, 3], axis=1), 2.0)
    assert streams["source+2m"]["offset_m"] == 2.0
    assert streams["source+2m"]["iteration"] == rendered["params"]["source_checkpoint"]
    for name, s in streams.items():
        if s["kind"] in ("condition", "target") or name == "source+0m":
            assert np.allclose(geometry.as_pose(s["c2w"]), recorded)
    # the shifted view differs from the recorded one rendered by the same checkpoint
    a = read_image(rendered["dir"] / "renders/front/source+0m" / f"{frames[0]:06d}.png")
    b = read_image(rendered["dir"] / "renders/front/source+2m" / f"{frames[0]:06d}.png")
    assert np.abs(a.astype(int) - b).mean() > 3


def test_depth_exr_holds_metric_z_depth_close_to_the_truth(rendered):
    import OpenEXR

    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.uri import parse_uri

    cam = rendered["doc"]["cameras"]["front"]
    frames = cam["frames"][::3]
    depth = []
    for pos in frames:
        with OpenEXR.File(str(rendered["dir"] / "renders/front/source+0m/depth" / f"{pos:06d}.exr")) as f:
            z = f.channels()["Z"].pixels
        assert z.dtype == np.float32 and z.shape == (96, 160)
        depth.append(z)
    street = street_from_uri(parse_uri(SCENE), rendered["ingest"])
    scene = load_scene(rendered["dir"])
    fx, fy, cx, cy = cam["intrinsics"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    truth = street.render(scene.c2w("front")[frames], K, 160, 96, frames=frames)["depth"]
    depth = np.stack(depth)
    solid, surface = np.isfinite(truth), np.isfinite(depth)
    both = solid & surface
    assert both.sum() > 0.7 * solid.sum()            # most of the street renders as a surface
    assert np.isinf(depth[~solid]).mean() > 0.8       # and the sky as sky (+inf, like the truth)
    rel = np.abs(depth[both] - truth[both]) / truth[both]
    assert np.median(rel) < 0.3, f"median relative depth error {np.median(rel):.3f}"
    assert np.corrcoef(np.log(depth[both]), np.log(truth[both]))[0, 1] > 0.8
    # the condition streams have depth too, the target (a camera log) has none
    assert (rendered["dir"] / "renders/front" / f"cond@{rendered['params']['condition_checkpoints'][0]:06d}"
            / "depth" / f"{frames[0]:06d}.exr").is_file()
    assert not (rendered["dir"] / "renders/front/target/depth").exists()


def test_alpha_is_written_when_asked(rendered):
    scene_dir = rendered["dir"]
    cam = rendered["doc"]["cameras"]["front"]
    pos = cam["frames"][0]
    alpha = read_image(scene_dir / "renders/front/source+2m/alpha" / f"{pos:06d}.png")
    assert alpha.shape == (96, 160, 3)
    # the stored alpha is the rasterizer's alpha of that shifted view, quantised to 8 bits
    scene = load_scene(scene_dir)
    shifted = geometry.lateral_shift(scene.c2w("front")[[pos]], scene.ego2world()[[pos]], 2.0)
    fx, fy, cx, cy = cam["intrinsics"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    model = fitted_model(scene_dir, rendered["params"]["source_checkpoint"])
    expected = next(render_views(model, shifted, K, 160, 96, frames=[pos]))["alpha"][0]
    assert np.abs(alpha[..., 0] / 255.0 - expected).max() <= 1.0 / 255 + 1e-6
    # the sky dome closes the view: few pixels show the empty background through more than half
    assert (expected >= 0.5).mean() > 0.95 and expected.mean() > 0.85, (expected.min(), expected.mean())


def test_batch_size_does_not_change_the_renders(rendered):
    scene_dir = rendered["dir"]
    it = rendered["params"]["source_checkpoint"]
    model = fitted_model(scene_dir, it)
    cam = rendered["doc"]["cameras"]["front"]
    fx, fy, cx, cy = cam["intrinsics"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    c2w = load_scene(scene_dir).c2w("front")[cam["frames"][:3]]
    static = model.params   # the background alone: cameras of several frames share a pass
    batched = list(render_views(static, c2w, K, 160, 96, batch_frames=3))
    single = list(render_views(static, c2w, K, 160, 96, batch_frames=1))
    assert len(batched) == 1 and len(single) == 3
    diff = np.abs(batched[0]["rgb"].astype(int) - np.concatenate([s["rgb"] for s in single]))
    assert diff.max() <= 1
    # a scene graph renders frame by frame whatever the batch, as the render stage wrote it
    frames = cam["frames"][:3]
    batched = list(render_views(model, c2w, K, 160, 96, frames=frames, batch_frames=3))
    single = list(render_views(model, c2w, K, 160, 96, frames=frames, batch_frames=1))
    assert model.dynamic and len(batched) == len(single) == 3
    assert all(np.array_equal(a["rgb"], b["rgb"]) for a, b in zip(batched, single))
    stored = read_image(scene_dir / "renders/front/source+0m" / f"{cam['frames'][0]:06d}.png")
    assert np.abs(stored.astype(int) - batched[0]["rgb"][0]).max() <= 1


def test_a_narrower_output_crops_the_same_picture(rendered):
    """Rendering at a cropped aspect with the adjusted intrinsics equals cropping the full render."""
    scene_dir = rendered["dir"]
    scene = load_scene(scene_dir)
    c = scene.cameras["front"]
    it = rendered["params"]["source_checkpoint"]
    model = fitted_model(scene_dir, it)
    c2w = scene.c2w("front")[:1]
    full = next(render_views(model, c2w, c.K(), c.width, c.height, frames=[0]))["rgb"][0]
    out = output_camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, 128, 96)
    x0 = out.crop[0]
    narrow = next(render_views(model, c2w, out.K, 128, 96, frames=[0]))["rgb"][0]
    assert np.abs(narrow.astype(int) - full[:, x0:x0 + 128]).mean() < 1.0
    target = crop_resize(scene.load_image(0, "front"), out)
    assert np.array_equal(target, scene.load_image(0, "front")[:, x0:x0 + 128])


def test_missing_checkpoint_names_the_file_and_the_fix(rendered, copy_tree):
    scene_dir = copy_tree(rendered["dir"])
    it = rendered["params"]["condition_checkpoints"][0]
    (scene_dir / "gs" / f"ckpt_{it:06d}.ply").unlink()
    with pytest.raises(SceneError) as err:
        render_scene(scene_dir, stage_params("render", rendered["params"]))
    text = str(err.value)
    assert f"ckpt_{it:06d}.ply" in text and "fit.checkpoints" in text and SID in text
    # the renders already there are untouched
    assert (scene_dir / "renders" / "renders.json").is_file()


def test_unknown_camera_is_a_scene_error(rendered, copy_tree):
    scene_dir = copy_tree(rendered["dir"])
    with pytest.raises(SceneError, match="side_left"):
        render_scene(scene_dir, stage_params("render", {**rendered["params"], "cameras": ["front", "side_left"]}))


def test_short_scene_skips_its_clips_with_a_reason(rendered, copy_tree):
    scene_dir = copy_tree(rendered["dir"])
    summary = render_scene(scene_dir, stage_params("render", {**rendered["params"], "clip_frames": 30})).summary()
    doc = json.loads((scene_dir / "renders" / "renders.json").read_text())
    cam = doc["cameras"]["front"]
    assert summary["skipped_clips"] == 1 and cam["windows"] == [] and cam["streams"] == {}
    assert cam["skipped"] == [{"clip": "middle", "reason": "scene has 24 frames, a clip needs 30"}]
    assert not (scene_dir / "renders" / "front").exists()


def test_the_ego_mask_shows_the_recorded_pixels_in_every_stream(rendered, copy_tree):
    """A video's hood moves with the camera: under the ego mask every stream (sources at any
    offset, conditions) shows the recorded frame's pixels, as the target does. Here a magenta
    band painted into the recorded frames after the fit, which no checkpoint has seen."""
    from paradrive.contracts.layout import SceneLayout
    from paradrive.scene import write_image

    scene_dir = copy_tree(rendered["dir"])
    scene = load_scene(scene_dir)
    cam = scene.cameras["front"]
    band = np.zeros((cam.height, cam.width), dtype=bool)
    band[-12:] = True
    for pos in range(len(scene.frames)):
        pixels = scene.load_image(pos, "front").copy()
        pixels[band] = (230, 20, 230)
        write_image(scene.image_path(pos, "front"), pixels)
    write_image(SceneLayout(scene_dir).ego_mask("front"), band.astype(np.uint8)[..., None] * 255)
    render_scene(scene_dir, stage_params("render", rendered["params"]))
    doc = json.loads((scene_dir / "renders" / "renders.json").read_text())
    cam_doc = doc["cameras"]["front"]
    scene = load_scene(scene_dir)
    for pos in cam_doc["frames"][::3]:
        recorded = scene.load_image(pos, "front")
        for name in cam_doc["streams"]:
            png = read_image(scene_dir / "renders" / "front" / name / f"{pos:06d}.png")
            assert np.abs(png[band].astype(int) - recorded[band]).max() <= 1, (name, pos)
            # above the band the model's own picture, which never saw magenta
            if name != "target":
                above = png[-20:-12].astype(int)
                assert np.abs(above - (230, 20, 230)).sum(-1).min() > 60, (name, pos)
