"""The scene graph: background Gaussians in the world plus one rigid node per moving actor.

A node's Gaussians live in its actor's box frame (origin at the box centre, x along the heading,
z up; :mod:`paradrive.actors`). At scene frame ``f`` (a position in ``scene.json``'s ``frames``)
:func:`place` moves them by the actor's ``box2world`` at that frame and returns one set of
Gaussians in the world, so background and actors are rasterized together in one pass and their
depth order is right. A node whose actor has no box at ``f`` (not yet seen, or gone) is left out
of that frame.

The model is a flat parameter set (the layout of :mod:`paradrive.gs.model`) and ``node`` (N,)
int64, the node of each Gaussian (:data:`BACKGROUND` for the world's own, the sky dome included),
so densification, pruning and the Adam moments work on it unchanged, per Gaussian in its own
frame. View-dependent colour (SH bands above 0) is evaluated with world directions for every
Gaussian; a turning car keeps its base colour exactly and its view-dependent part approximately.

Checkpoints (:func:`save_model` / :func:`load_model`)::

    gs/ckpt_<iteration:06d>.ply                     background and sky, in the world (any 3DGS viewer)
    gs/actors/ckpt_<iteration:06d>/<actor>.ply      one per node, in its box frame

``fit.json`` lists the nodes (``actors``: id, class, file); a renderer places each by its track.

Credit: the scene graph of OmniRe (Chen et al.) in DriveStudio, which the ReCamDriving recipe
keeps; its rigid nodes are followed here, its SMPL bodies and deformation fields are not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from paradrive import geometry
from paradrive.errors import SceneError

from .model import PARAM_KEYS, Gaussians

if TYPE_CHECKING:
    from paradrive.actors import Actor

    from .init import View
    from paradrive.contracts.layout import SceneLayout
    from paradrive.contracts.records import FitRecord

__all__ = ["BACKGROUND", "NodePoses", "NodeRows", "FittedModel", "node_poses", "place", "save_model", "load_model",
           "boxes_containing"]

BACKGROUND = -1
BOX_REFINEMENT = "box_refinement.npy"   # beside a checkpoint's node PLYs, when boxes are refined
# a point this close above a box's floor still belongs to the road it stands on
FLOOR_MARGIN_M = 0.1


@dataclass
class NodePoses:
    """Where each node is at each scene frame.

    ids: node k's actor id; box2world (F, K, 4, 4) float32 (identity where absent); present
    (F, K) bool; quats (F, K, 4) the rotations as w x y z.
    """

    ids: list[str]
    box2world: torch.Tensor
    present: torch.Tensor
    quats: torch.Tensor

    def to(self, device: torch.device | str) -> NodePoses:
        return NodePoses(self.ids, self.box2world.to(device), self.present.to(device),
                         self.quats.to(device))

    def __len__(self) -> int:
        return len(self.ids)

    def at(self, frame: int, correction: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(box2world (K, 4, 4), rotation quaternions (K, 4)) of every node at ``frame``.

        correction: None, or (F, K, 4) per frame and node a box refinement (dx, dy, dz in the
        world, metres; a turn about the box's z axis, radians): box2world becomes
        T(d) box2world Rz(yaw). Differentiable in ``correction``.
        """
        box, quats = self.box2world[frame], self.quats[frame]
        if correction is None:
            return box, quats
        c = correction[frame].to(box.device)
        yaw = c[:, 3]
        cos, sin, zero, one = torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw), torch.ones_like(yaw)
        rz = torch.stack([cos, -sin, zero, sin, cos, zero, zero, zero, one], -1).reshape(-1, 3, 3)
        rot = box[:, :3, :3] @ rz
        top = torch.cat([rot, (box[:, :3, 3] + c[:, :3])[:, :, None]], 2)
        bottom = box[:, 3:4, :]
        half = 0.5 * yaw
        qz = torch.stack([torch.cos(half), zero, zero, torch.sin(half)], -1)
        return torch.cat([top, bottom], 1), quat_multiply(quats, qz)

    def corrected(self, correction: torch.Tensor) -> NodePoses:
        """These poses with a box refinement (F, K, 4) (see :meth:`at`) applied at every frame."""
        with torch.no_grad():
            pairs = [self.at(f, correction) for f in range(len(self.box2world))]
        return NodePoses(self.ids, torch.stack([b for b, _ in pairs]), self.present,
                         torch.stack([q for _, q in pairs]))


def node_poses(scene, actors: Sequence[Actor]) -> NodePoses:
    """The poses of ``actors`` at every frame of ``scene`` (by frame position), on the CPU."""
    position = {f.index: i for i, f in enumerate(scene.frames)}
    n_frames, k = len(scene.frames), len(actors)
    poses = np.tile(np.eye(4), (n_frames, k, 1, 1))
    present = np.zeros((n_frames, k), dtype=bool)
    for j, actor in enumerate(actors):
        for frame, pose in zip(actor.frames, actor.box2world):
            if int(frame) in position:
                poses[position[int(frame)], j] = pose
                present[position[int(frame)], j] = True
    quats = np.zeros((n_frames, k, 4))
    quats[..., 0] = 1.0
    for f, j in zip(*np.nonzero(present)):
        quats[f, j] = geometry.rotation_to_quaternion(poses[f, j, :3, :3])
    return NodePoses([a.id for a in actors], torch.tensor(poses, dtype=torch.float32, device="cpu"),
                     torch.tensor(present, device="cpu"),
                     torch.tensor(quats, dtype=torch.float32, device="cpu"))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of quaternions (..., 4) w x y z (rotation ``a`` after ``b``)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


@dataclass(frozen=True)
class NodeRows:
    """The rows of the Gaussians in nodes (``node >= 0``) and their nodes: what :func:`place`
    computes from ``node``, kept by a caller that places the same Gaussians at many frames."""

    node: torch.Tensor
    version: int
    rows: torch.Tensor   # (M,) int64
    k: torch.Tensor      # (M,) int64, node of each row

    @classmethod
    def of(cls, node: torch.Tensor, known: NodeRows | None = None) -> NodeRows:
        """Those of ``node``: ``known`` when it was made from this tensor, unchanged since."""
        if known is not None and known.node is node and known.version == node._version:
            return known
        rows = torch.nonzero(node >= 0).squeeze(1)
        return cls(node, node._version, rows, node.index_select(0, rows))


def place(params: Gaussians, node: torch.Tensor | None, poses: NodePoses | None,
          frame: int, correction: torch.Tensor | None = None,
          rows: NodeRows | None = None) -> Gaussians:
    """The Gaussians of scene frame ``frame`` in the world.

    Background Gaussians (``node == BACKGROUND``) as they are; node k's moved by its box2world at
    ``frame`` (refined by ``correction``, see :meth:`NodePoses.at`); those of nodes absent there
    hidden (opacity 0: no rasterizer draws them, and they get no gradient). Every Gaussian stays,
    in its place, so only the nodes' rows are computed (a street's background is most of them).
    Differentiable in ``params`` and ``correction``. ``rows``: :meth:`NodeRows.of` ``node``,
    when the caller keeps them.

    On the CPU with the native kernels (and no ``correction``) one call places them and one
    computes their gradients, those of the torch expressions of :func:`_place_torch` to float32
    rounding:
    in the demo's fit (150k Gaussians, 16k in nodes) about 0.5 ms forward and 0.8 ms backward,
    against 2.5 and 3.5 ms as torch operations. Those gather and write the rows whole
    (index_select, index_copy), not element by element through advanced indexing (7.4 ms
    forward that way).
    """
    if poses is None or node is None or not len(poses):
        return params
    out = {k: params[k] for k in PARAM_KEYS}
    rows = NodeRows.of(node, rows)
    if not len(rows.rows):
        return out
    kernels = _place_kernels(params, poses, correction)
    if kernels is not None:
        out["means"], out["quats"], out["opacities"] = _Place.apply(
            params["means"], params["quats"], params["opacities"], rows, poses, frame, kernels)
        return out
    return _place_torch(params, out, rows, poses, frame, correction)


def _place_torch(params: Gaussians, out: dict, rows: NodeRows, poses: NodePoses, frame: int,
                 correction: torch.Tensor | None) -> Gaussians:
    """:func:`place` as torch operations, on any device: ``out`` (the parameters) gets the
    placed means, quats and opacities."""
    dev = params["means"].device
    idx, k = rows.rows, rows.k
    box, quats = poses.at(frame, correction)
    box = box.to(dev).index_select(0, k)
    means = (torch.einsum("nij,nj->ni", box[:, :3, :3], params["means"].index_select(0, idx))
             + box[:, :3, 3])
    out["means"] = params["means"].index_copy(0, idx, means)
    out["quats"] = params["quats"].index_copy(0, idx, quat_multiply(
        quats.to(dev).index_select(0, k), params["quats"].index_select(0, idx)))
    hidden = idx[~poses.present[frame].to(dev).index_select(0, k)]
    if len(hidden):
        out["opacities"] = params["opacities"].index_fill(0, hidden, -math.inf)
    return out


def _place_kernels(params: Gaussians, poses: NodePoses, correction: torch.Tensor | None):
    """The native kernels where they place these Gaussians (float32 on the CPU, poses there too,
    no box refinement, the library built), else None."""
    tensors = [params[k] for k in ("means", "quats", "opacities")] + [poses.box2world, poses.quats]
    if correction is not None or any(t.device.type != "cpu" or t.dtype != torch.float32
                                     for t in tensors):
        return None
    from paradrive import kernels

    return kernels.load()


class _Place(torch.autograd.Function):
    """:func:`place` as one node: inputs means (N, 3), quats (N, 4), opacities (N,), the
    NodeRows, the NodePoses, the frame and the kernels; outputs the three placed."""

    @staticmethod
    def forward(ctx, means, quats, opacities, rows: NodeRows, poses: NodePoses, frame: int,
                kernels):
        from paradrive.devices import cpu_kernel_threads

        if int(rows.k.max()) >= len(poses):
            raise ValueError(f"place: a Gaussian of node {int(rows.k.max())}, but "
                             f"{len(poses)} nodes have poses")
        node_args = (rows.rows.contiguous().numpy(), rows.k.contiguous().numpy(),
                     poses.box2world[frame].contiguous().numpy(),
                     poses.quats[frame].contiguous().numpy(),
                     poses.present[frame].contiguous().numpy())
        placed = kernels.place_forward(*(t.detach().contiguous().numpy()
                                         for t in (means, quats, opacities)),
                                       *node_args, cpu_kernel_threads())
        ctx.node_args, ctx.kernels = node_args, kernels
        return tuple(torch.from_numpy(a) for a in placed)

    @staticmethod
    def backward(ctx, g_means, g_quats, g_opacities):
        from paradrive.devices import cpu_kernel_threads

        wanted = ctx.needs_input_grad[:3]
        grads = [None if g is None or not w else g.to(torch.float32).contiguous().numpy()
                 for g, w in zip((g_means, g_quats, g_opacities), wanted)]
        if all(g is None for g in grads):
            return None, None, None, None, None, None, None
        out = ctx.kernels.place_backward(*grads, *ctx.node_args, cpu_kernel_threads())
        return (*(None if a is None else torch.from_numpy(a) for a in out), None, None, None, None)


def boxes_containing(points: np.ndarray, actors: Sequence[Actor], frame_index: int,
                     ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Which ``points`` (M, 3) world lie in the actors' boxes at scene frame ``frame_index``.

    Returns (inside_any (M,) bool, per actor the box-frame coordinates of its points (Mk, 3)).
    A point within ``FLOOR_MARGIN_M`` of a box's floor belongs to the road, not the actor.
    """
    inside = np.zeros(len(points), dtype=bool)
    local: list[np.ndarray] = []
    for actor in actors:
        pose = actor.pose_at(frame_index)
        if pose is None or not len(points):
            local.append(np.zeros((0, 3)))
            continue
        p = (points - pose[:3, 3]) @ pose[:3, :3]
        half = 0.5 * np.asarray(actor.size, dtype=np.float64)
        hit = ((np.abs(p[:, :2]) <= half[:2]).all(1) & (p[:, 2] <= half[2])
               & (p[:, 2] >= -half[2] + FLOOR_MARGIN_M))
        inside |= hit
        local.append(p[hit])
    return inside, local


# --------------------------------------------------------------------------- checkpoints

@dataclass
class FittedModel:
    """A checkpoint as a renderer takes it: flat parameters, each Gaussian's node and the poses
    (None for a static fit)."""

    params: Gaussians
    node: torch.Tensor | None = None
    poses: NodePoses | None = None
    _rows: NodeRows | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def dynamic(self) -> bool:
        return self.poses is not None and len(self.poses) > 0

    def to(self, device: torch.device | str) -> FittedModel:
        return FittedModel({k: v.to(device) for k, v in self.params.items()},
                           None if self.node is None else self.node.to(device),
                           None if self.poses is None else self.poses.to(device))

    def at(self, frame: int | None) -> Gaussians:
        """The Gaussians of scene frame ``frame`` in the world (any frame for a static model)."""
        if not self.dynamic:
            return self.params
        if frame is None:
            raise ValueError("a scene-graph checkpoint renders at a frame: pass the frames")
        if self.node is not None:
            self._rows = NodeRows.of(self.node, self._rows)
        return place(self.params, self.node, self.poses, int(frame), rows=self._rows)


def save_model(layout: SceneLayout, iteration: int, params: Gaussians, node: torch.Tensor | None,
               files: Sequence[str], correction: torch.Tensor | None = None) -> None:
    """The background checkpoint PLY and, per node k, ``gs/actors/ckpt_<it>/<files[k]>``; with a
    box refinement, its (F, K, 4) values in ``gs/actors/ckpt_<it>/box_refinement.npy``."""
    from paradrive.io import atomic_path

    from .ply import save_ply

    if correction is not None:
        path = layout.actor_checkpoint(iteration, BOX_REFINEMENT)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.save(f, correction.detach().to("cpu").numpy().astype(np.float32))

    if node is None:
        save_ply(layout.checkpoint(iteration), params)
        return
    node = node.to("cpu")
    pick = {k: v.detach().to("cpu") for k, v in params.items() if k in PARAM_KEYS}
    for k, file in enumerate(files):
        path = layout.actor_checkpoint(iteration, file)
        path.parent.mkdir(parents=True, exist_ok=True)
        save_ply(path, {key: v[node == k] for key, v in pick.items()})
    # the background last: its PLY is the checkpoint a skip check looks for
    save_ply(layout.checkpoint(iteration), {k: v[node == BACKGROUND] for k, v in pick.items()})


def load_model(layout: SceneLayout, iteration: int, scene, fit: FitRecord | None) -> FittedModel:
    """The checkpoint of ``iteration``: the background PLY plus, when ``fit`` lists actor nodes,
    each node's PLY placed by the scene's tracks."""
    from .ply import load_checkpoint

    sid = scene.scene_id
    params = load_checkpoint(layout.checkpoint(iteration), scene_id=sid)
    nodes = fit.actors if fit is not None else []
    if not nodes:
        return FittedModel(params)
    by_id = {a.id: a for a in scene.actors}
    missing = [n.id for n in nodes if n.id not in by_id]
    if missing:
        raise SceneError(f"fit.json names actor {missing[0]}, which scene.json does not have",
                         scene_id=sid, path=layout.fit_json, fix="re-run the fit stage")
    parts, node = [params], [torch.full((len(params["means"]),), BACKGROUND, dtype=torch.int64,
                                        device="cpu")]
    for k, n in enumerate(nodes):
        path = layout.actor_checkpoint(iteration, n.file)
        part = load_checkpoint(path, scene_id=sid)
        parts.append(part)
        node.append(torch.full((len(part["means"]),), k, dtype=torch.int64, device="cpu"))
    flat = {key: torch.cat([p[key] for p in parts]) for key in PARAM_KEYS}
    poses = node_poses(scene, [by_id[n.id] for n in nodes])
    refined = layout.actor_checkpoint(iteration, BOX_REFINEMENT)
    if refined.is_file():
        correction = torch.from_numpy(np.load(refined)).float()
        if tuple(correction.shape) != (len(scene.frames), len(nodes), 4):
            raise SceneError(f"box refinement has shape {tuple(correction.shape)}, not "
                             f"({len(scene.frames)}, {len(nodes)}, 4)", scene_id=sid, path=refined,
                             fix="re-run the fit stage")
        poses = poses.corrected(correction)
    return FittedModel(flat, torch.cat(node), poses)


# --------------------------------------------------------------------------- initialisation

def _voxel_thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per ``voxel``-sized cell (the first in sorted order): deterministic thinning."""
    if voxel <= 0 or not len(points):
        return points
    points = points[np.lexsort((points[:, 2], points[:, 1], points[:, 0]))]
    _, first = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def actor_points_init(actor: Actor, local: np.ndarray, views: Sequence[View], *, n_points: int,
                      voxel: float, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial points of an actor node in its box frame, and their colours.

    local: LiDAR returns inside the box over the track (box frame, (M, 3)); thinned to one per
    ``voxel`` and at most ``n_points`` drawn with ``generator``. With fewer than a tenth of
    ``n_points`` (no LiDAR, or a far actor) the rest are drawn uniformly in the box. Colours come
    from the nearest views (by the box's distance) of frames where the actor is tracked.
    """
    pts = torch.from_numpy(_voxel_thin(np.asarray(local, dtype=np.float64), voxel)).float()
    if len(pts) > n_points:
        pts = pts[torch.randperm(len(pts), generator=generator)[:n_points].sort().values]
    if len(pts) < max(1, n_points // 10):
        half = torch.tensor(0.5 * np.asarray(actor.size), dtype=torch.float32)
        fill = (torch.rand(n_points - len(pts), 3, generator=generator) * 2.0 - 1.0) * half
        pts = torch.cat([pts, fill])
    return pts, _actor_colours(actor, pts, views)


def _actor_colours(actor: Actor, pts: torch.Tensor, views: Sequence[View],
                   max_views: int = 24) -> torch.Tensor:
    """Colours of box-frame points from the ``max_views`` views nearest the box among those
    whose frame the actor is tracked in, nearest first."""
    from .init import colours_from_views

    seen = []
    for view in views:
        pose = actor.pose_at(view.frame_index) if view.frame_index is not None else None
        if pose is not None:
            seen.append((float(np.linalg.norm(view.c2w[:3, 3].numpy() - pose[:3, 3])), view, pose))
    nearest = sorted(seen, key=lambda s: s[0])[:max_views]
    return colours_from_views(pts, [v for _, v, _ in nearest], default=0.5, skip_sky=False,
                              poses=[pose for _, _, pose in nearest])
