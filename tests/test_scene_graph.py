"""The scene graph: background plus one rigid node per moving actor, placed by its track."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from test_gs_fit import TINY_FIT, _copy_scene, fit_params

from paradrive import geometry
from paradrive.actors import Actor, box_footprint, is_moving
from paradrive.stages.fit import fit_scene
from paradrive.gs.graph import BACKGROUND, FittedModel, NodePoses, NodeRows, load_model, place
from paradrive.gs.model import new_params
from paradrive.gs.strategy import DensifyStrategy
from paradrive.gs.views import render_views
from paradrive.scene import load_scene
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import FitRecord


def _poses(mats: list[list[np.ndarray | None]]) -> NodePoses:
    """NodePoses from [frame][node] box2world (None = absent)."""
    f, k = len(mats), len(mats[0])
    box = torch.eye(4).repeat(f, k, 1, 1)
    present = torch.zeros(f, k, dtype=torch.bool)
    quats = torch.tensor([1.0, 0, 0, 0]).repeat(f, k, 1)
    for i, row in enumerate(mats):
        for j, m in enumerate(row):
            if m is not None:
                box[i, j] = torch.from_numpy(m).float()
                present[i, j] = True
                quats[i, j] = torch.from_numpy(geometry.rotation_to_quaternion(m[:3, :3])).float()
    return NodePoses([f"a{j}" for j in range(k)], box, present, quats)


def _gaussians(means, rgb, scale=0.3):
    means = torch.tensor(means, dtype=torch.float32)
    return new_params(means, torch.tensor(rgb, dtype=torch.float32).expand(len(means), 3),
                      torch.full((len(means), 3), scale), opacity=0.99, sh_degree=0)


def test_a_node_is_moved_by_its_box_pose_and_hidden_where_absent():
    params = _gaussians([[0.0, 0.0, 5.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [0.5, 0.5, 0.5])
    params["means"].requires_grad_(True)
    params["opacities"].requires_grad_(True)
    node = torch.tensor([BACKGROUND, 0, 1])
    turn = geometry.make_pose(geometry.rotation_about("z", math.pi / 2), [10.0, 0.0, 0.0])
    poses = _poses([[turn, None], [turn, turn]])

    out = place(params, node, poses, 0)
    torch.testing.assert_close(out["means"][0], params["means"][0])    # the background stays
    torch.testing.assert_close(out["means"][1], torch.tensor([10.0, 1.0, 0.0]))
    # the Gaussian's rotation turns with its box: identity local -> the box's own quaternion
    torch.testing.assert_close(out["quats"][1], poses.quats[0, 0])
    # node 1 has no box at frame 0: its Gaussian is hidden, the others keep their opacity
    assert torch.sigmoid(out["opacities"]).tolist()[2] == 0.0
    torch.testing.assert_close(out["opacities"][:2], params["opacities"][:2])
    (out["means"][1].sum() + out["means"][2].sum() + out["opacities"].sum()).backward()
    assert params["means"].grad[1].abs().sum() > 0      # differentiable in the local parameters
    assert params["opacities"].grad[2] == 0 and params["opacities"].grad[1] != 0

    out = place(params, node, poses, 1)
    assert bool(torch.isfinite(out["opacities"]).all())
    torch.testing.assert_close(out["means"][2], torch.tensor([10.0, 2.0, 0.0]))


def test_kept_node_rows_place_as_fresh_ones_until_the_nodes_change():
    params = _gaussians([[0.0, 0.0, 5.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], [0.5, 0.5, 0.5])
    turn = geometry.make_pose(geometry.rotation_about("z", math.pi / 2), [10.0, 0.0, 0.0])
    poses = _poses([[turn, turn], [turn, None]])
    node = torch.tensor([BACKGROUND, 0, 1])
    kept = NodeRows.of(node)
    assert NodeRows.of(node, kept) is kept
    for frame in (0, 1):
        fresh, reused = place(params, node, poses, frame), place(params, node, poses, frame, rows=kept)
        assert all(torch.equal(fresh[k], reused[k]) for k in fresh)
    node[0] = 1     # changed in place: its rows are taken again
    again = NodeRows.of(node, kept)
    assert again is not kept and again.rows.tolist() == [0, 1, 2] and again.k.tolist() == [1, 0, 1]
    assert NodeRows.of(node.clone(), again) is not again
    moved = place(params, node, poses, 0, rows=again)
    torch.testing.assert_close(moved["means"][0], torch.tensor([10.0, 0.0, 5.0]))


@pytest.mark.parametrize("threads", [1, 2])
def test_native_placement_matches_the_torch_expressions(threads):
    """On the CPU one native call places the nodes and one computes their gradients: within
    float32 rounding of the torch expressions (any device's path), forward and backward (means
    1e-5 absolute at 20 m, quats and gradients 1e-5 relative; a product's rounding differs
    where torch fuses or orders the sums otherwise), and the same bytes on 1 and 2 threads;
    rows outside the nodes keep their inputs and gradients exactly."""
    from paradrive.devices import set_cpu_kernel_threads
    from paradrive import kernels
    from paradrive.gs import graph

    gen = torch.Generator().manual_seed(3)
    n, k = 40000, 5       # rows of nodes span several of the kernel's chunks
    params = {"means": torch.randn(n, 3, generator=gen) * 20, "quats": torch.randn(n, 4, generator=gen),
              "opacities": torch.randn(n, generator=gen), "scales": torch.randn(n, 3, generator=gen),
              "sh0": torch.randn(n, 1, 3, generator=gen), "shN": torch.zeros(n, 0, 3)}
    for key in ("means", "quats", "opacities"):
        params[key].requires_grad_(True)
    node = torch.randint(-1, k, (n,), generator=gen)
    angles = torch.rand(2, k, generator=gen).double() * 6.28
    poses = _poses([[None if (f, j) == (0, 3) else geometry.make_pose(
        geometry.rotation_about("z", float(angles[f, j])) @ geometry.rotation_about("x", 0.1 * j),
        [30.0 * j, -4.0, 0.5]) for j in range(k)] for f in range(2)])
    outputs = [torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen),
               torch.randn(n, generator=gen)]
    for g in outputs:
        g.view(-1)[::7] = -0.0
    inputs = [params[key] for key in ("means", "quats", "opacities")]
    assert graph._place_kernels(params, poses, None) is kernels.load() is not None
    keys, free = ("means", "quats", "opacities"), node < 0
    runs = []
    old = set_cpu_kernel_threads(threads)
    try:
        for frame in (0, 1):
            native = place(params, node, poses, frame)
            reference = graph._place_torch(params, dict(params), NodeRows.of(node), poses, frame, None)
            assert type(native["means"].grad_fn).__name__ == "_PlaceBackward"
            grads = [torch.autograd.grad([out[key] for key in keys], inputs, outputs)
                     for out in (native, reference)]
            for key, a, b in zip(keys, (native[k].detach() for k in keys),
                                 (reference[k].detach() for k in keys)):
                torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
                assert torch.equal(a[free], b[free]), key
            for key, a, b in zip(keys, *grads):
                torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
                assert torch.equal(a[free], b[free]), key
            runs.append([native[k].detach() for k in keys] + list(grads[0]))
        assert bool(torch.isinf(place(params, node, poses, 0)["opacities"][node == 3]).all())
        set_cpu_kernel_threads(3 - threads)  # the other thread count: the same bytes
        for frame, run in zip((0, 1), runs):
            again = place(params, node, poses, frame)
            again_grads = torch.autograd.grad([again[k] for k in keys], inputs, outputs)
            for a, b in zip([again[k].detach() for k in keys] + list(again_grads), run):
                assert torch.equal(a, b)
    finally:
        set_cpu_kernel_threads(old)


def _render(model: FittedModel, frames: list[int]) -> np.ndarray:
    K = np.array([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    c2w = np.repeat(np.eye(4)[None], len(frames), 0)
    return np.concatenate([r["rgb"] for r in render_views(model, c2w, K, 64, 48, frames=frames,
                                                          batch_frames=4)])


def test_a_car_passing_in_front_of_a_facade_hides_it_in_the_same_pass():
    # a red facade 10 m ahead (background), a blue car node at its box centre
    xs = np.linspace(-3, 3, 13)
    wall = [[x, y, 10.0] for x in xs for y in xs]
    facade, car = _gaussians(wall, [1.0, 0.0, 0.0]), _gaussians([[0.0, 0.0, 0.0]], [0.0, 0.0, 1.0], 0.6)
    params = {k: torch.cat([facade[k], car[k]]) for k in facade}
    node = torch.tensor([BACKGROUND] * len(wall) + [0])
    in_front = geometry.translation(0.0, 0.0, 5.0)
    behind = geometry.translation(0.0, 0.0, 15.0)
    model = FittedModel(params, node, _poses([[in_front], [behind], [None]]))
    front, back, gone = _render(model, [0, 1, 2])
    centre = (24, 32)
    assert front[centre][2] > 200 and front[centre][0] < 50, "the car occludes the facade"
    assert back[centre][0] > 200 and back[centre][2] < 50, "the facade occludes the car"
    assert gone[centre][0] > 200, "an actor without a box at a frame is not drawn"
    with pytest.raises(ValueError, match="frames"):
        list(render_views(model, np.eye(4)[None], np.eye(3), 8, 8))


def test_gradients_of_a_partial_render_accumulate_on_the_rendered_gaussians():
    strategy = DensifyStrategy()
    state = strategy.initialize_state(5, 10.0)
    means2d = torch.ones(1, 2, 2, requires_grad=True)
    (means2d * torch.tensor([[[1.0, 0.0], [0.0, 2.0]]])).sum().backward()
    info = {"means2d": means2d, "n_cameras": 1, "width": 2, "height": 2,
            "radii": torch.ones(1, 2, dtype=torch.int32), "gaussian_ids": torch.tensor([1, 3])}
    strategy.update_state(state, info)
    assert state["count"].tolist() == [0.0, 1.0, 0.0, 1.0, 0.0]
    assert state["grad2d"][1] == pytest.approx(1.0) and state["grad2d"][3] == pytest.approx(2.0)


# --------------------------------------------------------------------------- fits

MOVING_M = 1.0   # ingest.moving_threshold_m's default


@pytest.fixture(scope="module")
def graph_fit(tiny_scene, tmp_path_factory):
    scene_dir = _copy_scene(tiny_scene, tmp_path_factory.mktemp("graph") / "scene")
    record = fit_scene(scene_dir, fit_params("smoke", **TINY_FIT, actor_init_points=200),
                       moving_threshold_m=MOVING_M)
    return scene_dir, record


def test_graph_fit_writes_the_background_and_each_node_in_its_box_frame(graph_fit):
    scene_dir, record = graph_fit
    scene = load_scene(scene_dir)
    moving = [a for a in scene.actors if is_moving(a, MOVING_M)]
    assert moving and record.dynamic
    assert [n.id for n in record.actors] == [a.id for a in moving]   # people too: nonrigid=rigid
    layout = SceneLayout(scene_dir)
    for it in TINY_FIT["checkpoints"]:
        model = load_model(layout, it, scene, record)
        assert model.dynamic and set(model.node.tolist()) == {BACKGROUND, *range(len(moving))}
        for k, actor in enumerate(moving):
            local = model.params["means"][model.node == k].numpy()
            # box frame: the node's Gaussians sit around the origin, within reach of its box
            # (in the world the actors are tens of metres away)
            assert (np.abs(local).max(0) <= 0.5 * actor.size + 2.0).all(), actor.id
            assert layout.actor_checkpoint(it, record.actors[k].file).is_file()


def test_background_init_leaves_the_moving_boxes_to_the_actors(tiny_scene):
    from paradrive.gs.fit import Graph, initial_model, load_views
    from paradrive.gs.graph import boxes_containing
    from paradrive.gs.model import scene_scale_of

    scene = load_scene(tiny_scene)
    p = fit_params("smoke", **TINY_FIT, actor_init_points=100)
    graph = Graph.of(scene, p, MOVING_M)
    views = load_views(scene, None, 2)
    raw, is_sky, node, init = initial_model(scene, views, p, scene_scale_of(scene.c2w("front")),
                                            __import__("logging").getLogger("test"), graph)
    background = raw["means"][(node == BACKGROUND) & ~is_sky].double().numpy()
    # the LiDAR init drops a moving actor's returns at the frame they were taken; with this
    # init every background point is outside every moving box at the frames the sweeps cover
    hits = [boxes_containing(background, graph.carved, f.index)[0].mean() for f in scene.frames]
    assert max(hits) < 0.01, hits
    assert init["actor_points"] and all(0 < n <= 100 for n in init["actor_points"])
    assert [int((node == k).sum()) for k in range(len(graph.nodes))] == init["actor_points"]


def _track(actor_id: str, cls: str, rigid: bool, xs) -> Actor:
    poses = np.stack([geometry.translation(float(x), 0.0, 0.8) for x in xs])
    return Actor(actor_id, cls, rigid, np.array([4.0, 2.0, 1.6]), np.arange(len(xs)), poses)


def test_dynamic_off_and_nonrigid_mask_change_the_graph():
    from types import SimpleNamespace

    from paradrive.gs.fit import Graph

    car, person = _track("car", "vehicle", True, [0, 2, 4]), _track("p", "pedestrian", False, [0, 1, 2])
    parked = _track("parked", "vehicle", True, [0, 0, 0])
    scene = SimpleNamespace(actors=[car, person, parked])
    assert Graph.of(scene, fit_params("smoke"), MOVING_M).nodes == [car, person]
    off = Graph.of(scene, fit_params("smoke", dynamic="off"), MOVING_M)
    assert off.nodes == [] and off.carved == []
    masked = Graph.of(scene, fit_params("smoke", nonrigid="mask"), MOVING_M)
    assert masked.nodes == [car] and masked.masked == [person]
    assert Graph.of(scene, fit_params("smoke"), None).nodes == []   # nothing counted as moving


def test_a_yaml_off_is_the_word_off():
    assert fit_params("smoke", dynamic=False).dynamic == "off"


def test_killed_graph_fit_resumes_to_byte_identical_node_checkpoints(graph_fit, tiny_scene, tmp_path):
    ref_dir, record = graph_fit
    scene_dir = _copy_scene(tiny_scene, tmp_path / "scene")
    p = fit_params("smoke", **TINY_FIT, actor_init_points=200)
    partial = fit_scene(scene_dir, p, moving_threshold_m=MOVING_M, stop_after=14)
    assert not partial.complete
    fit_scene(scene_dir, p, moving_threshold_m=MOVING_M)
    for it in TINY_FIT["checkpoints"]:
        ref = SceneLayout(ref_dir)
        got = SceneLayout(scene_dir)
        assert got.checkpoint(it).read_bytes() == ref.checkpoint(it).read_bytes()
        for n in record.actors:
            assert got.actor_checkpoint(it, n.file).read_bytes() == ref.actor_checkpoint(it, n.file).read_bytes()


# --------------------------------------------------------------------------- the smoke street

def _biggest_view(actor, scene, c2w: np.ndarray, K: np.ndarray, w: int, h: int) -> tuple[int, int]:
    """(pixels, frame position) of the frame where ``actor``'s box covers most of the view."""
    best = (0, -1)
    for pos, frame in enumerate(scene.frames):
        pose = actor.pose_at(frame.index)
        if pose is not None:
            best = max(best, (int(box_footprint(pose, actor.size, c2w[pos], K, w, h).sum()), pos))
    return best


def _node_alone(model: FittedModel, k: int) -> FittedModel:
    poses = model.poses
    return FittedModel({key: v[model.node == k] for key, v in model.params.items()},
                       torch.zeros(int((model.node == k).sum()), dtype=torch.int64),
                       NodePoses([poses.ids[k]], poses.box2world[:, k:k + 1], poses.present[:, k:k + 1],
                                 poses.quats[:, k:k + 1]))


def test_a_shifted_frame_shows_each_moving_car_where_it_was_at_that_time(smoke_scene):
    scene_dir = smoke_scene["data_dir"] / "scenes" / "synthetic-demo-s7"
    scene, layout = load_scene(scene_dir), SceneLayout(scene_dir)
    record = FitRecord.load(layout.fit_json)
    assert record.dynamic, "the smoke street has moving traffic: the fit is a scene graph"
    model = load_model(layout, record.iterations, scene, record)
    cam = scene.cameras["front"]
    K, w, h = cam.K(), cam.width, cam.height
    shifted = geometry.lateral_shift(scene.c2w("front"), scene.ego2world(), 2.0)
    ids = [n.id for n in record.actors]
    checked = contrasted = 0
    for car in (a for a in scene.actors if a.rigid and is_moving(a, MOVING_M)):
        area, pos = _biggest_view(car, scene, shifted, K, w, h)
        if area < 50:        # never more than a few pixels in view of the shifted camera
            continue
        k = ids.index(car.id)
        alone = _node_alone(model, k)

        def footprint(at: int, alone=alone, pos=pos) -> np.ndarray:
            view = next(render_views(alone, shifted[pos][None], K, w, h, frames=[at]))
            return view["alpha"][0] > 0.5

        truth = box_footprint(car.pose_at(scene.frames[pos].index), car.size, shifted[pos], K, w, h)
        drawn = footprint(pos)
        # the car's silhouette lies in its box (precision) and fills much of it (recall)
        inside, filled = (drawn & truth).sum() / max(drawn.sum(), 1), (drawn & truth).sum() / truth.sum()
        assert inside > 0.7 and filled > 0.35, (car.id, pos, inside, filled)
        # the same car drawn at another moment lands where its box was then, not where it is
        # now (the pixels only one of the two boxes covers decide): the test can fail
        here = model.poses.box2world[pos, k, :3, 3]
        moved = {f: float((model.poses.box2world[f, k, :3, 3] - here).norm())
                 for f in range(len(scene.frames)) if bool(model.poses.present[f, k])}
        away = max(moved, key=moved.__getitem__)
        then = box_footprint(car.pose_at(scene.frames[away].index), car.size, shifted[pos], K, w, h)
        only_now, only_then = truth & ~then, then & ~truth
        if moved[away] > car.size[0] and only_now.sum() >= 10 and only_then.sum() >= 10:
            wrong = footprint(away)
            assert (wrong & only_then).sum() > (wrong & only_now).sum(), (car.id, away)
            assert (drawn & only_now).sum() > (drawn & only_then).sum(), (car.id, pos)
            contrasted += 1
        checked += 1
    assert checked >= 2 and contrasted >= 1, "moving cars in view of the shifted camera"


def test_graph_fit_beats_the_static_fit_on_moving_actor_pixels(smoke_scene, tmp_path):
    import shutil

    from conftest import stage_params

    from paradrive.evaluation import evaluate_scene

    scene_dir = smoke_scene["data_dir"] / "scenes" / "synthetic-demo-s7"
    unrendered = shutil.ignore_patterns("renders", "clips", "eval")
    graph_dir = Path(shutil.copytree(scene_dir, tmp_path / "graph", ignore=unrendered))
    static_dir = Path(shutil.copytree(scene_dir, tmp_path / "static", ignore=unrendered))
    shutil.rmtree(static_dir / "gs")
    fit_scene(static_dir, fit_params("smoke", dynamic="off"))
    assert not FitRecord.load(SceneLayout(static_dir).fit_json).dynamic
    rp = stage_params("render", {"offsets_m": [2.0, -2.0]}, "smoke")
    docs = [evaluate_scene(d, rp, out_dir=tmp_path / f"eval-{d.name}", max_frames=8)
            for d in (graph_dir, static_dir)]
    rows = [[d["cameras"]["front"]["recorded"]] + d["cameras"]["front"]["shifted"] for d in docs]
    for graph_row, static_row in zip(*rows):
        assert graph_row["psnr_dynamic"] > static_row["psnr_dynamic"] + 2.0, (graph_row, static_row)
        assert graph_row["psnr_static"] > static_row["psnr_static"] - 0.5, (graph_row, static_row)
    saved = json.loads((tmp_path / "eval-graph" / "eval.json").read_text())
    assert saved["cameras"]["front"]["recorded"]["psnr_dynamic"] == rows[0][0]["psnr_dynamic"]


def test_a_deleted_actor_checkpoint_is_healed_by_a_plain_rerun(smoke_scene, copy_tree):
    from conftest import _build

    root = copy_tree(smoke_scene["root"], "healed")
    scene_dir = root / "data" / "scenes" / "synthetic-demo-s7"
    layout = SceneLayout(scene_dir)
    record = FitRecord.load(layout.fit_json)
    lost = layout.actor_checkpoint(record.iterations, record.actors[0].file)
    kept = layout.actor_checkpoint(record.iterations, record.actors[-1].file).read_bytes()
    lost.unlink()
    report = _build(root, smoke_scene["scene_uris"], stages=["ingest", "fit"])["report"]
    ran = {(r.stage, r.status) for r in report.results}
    assert ("fit", "done") in ran and ("ingest", "skipped") in ran, ran
    assert lost.is_file()
    assert layout.actor_checkpoint(record.iterations, record.actors[-1].file).read_bytes() == kept


# --------------------------------------------------------------------------- box refinement

def test_a_box_refinement_moves_and_turns_the_node():
    turn = geometry.make_pose(geometry.rotation_about("z", 0.3), [5.0, 1.0, 0.0])
    poses = _poses([[turn]])
    correction = torch.tensor([[[0.5, -0.2, 0.1, 0.2]]], requires_grad=True)
    box, quat = poses.at(0, correction)
    yaw = geometry.make_pose(geometry.rotation_about("z", 0.2), [0, 0, 0])
    expected = geometry.translation(0.5, -0.2, 0.1) @ turn @ yaw
    np.testing.assert_allclose(box[0].detach().numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(quat[0].detach().numpy(), geometry.rotation_to_quaternion(expected[:3, :3]),
                               atol=1e-6)
    params = _gaussians([[1.0, 0.0, 0.0]], [0.5, 0.5, 0.5])
    out = place(params, torch.tensor([0]), poses, 0, correction)
    out["means"].sum().backward()
    assert correction.grad is not None and correction.grad.abs().sum() > 0


def test_box_refinement_is_saved_applied_on_load_and_resumes_exactly(tiny_scene, tmp_path):
    p = fit_params("smoke", **{**TINY_FIT, "checkpoints": [10, 20]}, actor_pose_lr=0.01)
    dirs = [_copy_scene(tiny_scene, tmp_path / name) for name in ("a", "b")]
    fit_scene(dirs[0], p, moving_threshold_m=MOVING_M, stop_after=14)
    record = fit_scene(dirs[0], p, moving_threshold_m=MOVING_M)
    fit_scene(dirs[1], p, moving_threshold_m=MOVING_M)
    layout = SceneLayout(dirs[0])
    for it in (10, 20):
        files = [layout.actor_checkpoint(it, "box_refinement.npy")]
        files += [layout.actor_checkpoint(it, n.file) for n in record.actors] + [layout.checkpoint(it)]
        for path in files:
            assert path.read_bytes() == (dirs[1] / path.relative_to(dirs[0])).read_bytes(), path
    scene = load_scene(dirs[0])
    correction = np.load(layout.actor_checkpoint(20, "box_refinement.npy"))
    assert correction.shape == (len(scene.frames), len(record.actors), 4) and np.abs(correction).max() > 0
    refined = load_model(layout, 20, scene, record)
    f, k = np.argwhere(np.abs(correction[..., 0]) > 0)[0]
    actor = next(a for a in scene.actors if a.id == record.actors[k].id)
    label = actor.pose_at(scene.frames[f].index)
    np.testing.assert_allclose(refined.poses.box2world[f, k, :3, 3].numpy(),
                               label[:3, 3] + correction[f, k, :3], atol=1e-5)
    # without the refinement the same checkpoint would put the node at the label
    assert not np.allclose(refined.poses.box2world[f, k, :3, 3].numpy(), label[:3, 3], atol=1e-6)
