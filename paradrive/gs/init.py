"""Initial Gaussians: from LiDAR when a scene has it, else from the images alone, plus a sky dome.

All functions are deterministic given their ``torch.Generator``: a fit restarted from scratch
builds the very same initial model.

A *view* here is a :class:`View`: one training image with its camera (see ``fit.py``); the fit
never passes a held-out one (:class:`Holdout`), so no initialisation sees it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["View", "Holdout", "project", "knn_scales", "lidar_points_init", "frustum_points_init", "sky_dome",
           "colours_from_views"]


@dataclass
class View:
    """One training image. image: (H, W, 3) uint8; sky: (H, W) bool or None; K: (3, 3) pixels of
    this (possibly downscaled) image; c2w: (4, 4) float64 camera-to-world OpenCV."""

    image: torch.Tensor
    sky: torch.Tensor | None
    K: torch.Tensor
    c2w: torch.Tensor
    camera: str
    frame: int
    ground_z: float | None = None  # world z of the road under the vehicle (ego origin height)
    frame_index: int | None = None  # the scene frame's ``index`` (actor tracks use it)

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    def viewmat(self) -> torch.Tensor:
        """(4, 4) float32 world-to-camera."""
        return torch.linalg.inv(self.c2w).float()

    def rgb(self) -> torch.Tensor:
        """(H, W, 3) float32 in [0, 1]."""
        return self.image.float() / 255.0


@dataclass(frozen=True)
class Holdout:
    """The recorded views a fit leaves out to be evaluated on: every ``every``-th frame (frame
    positions every-1, 2*every-1, ..., as DriveStudio's test_image_stride; 0 = none) of every
    camera, and every frame of ``cameras``."""

    every: int = 0
    cameras: tuple[str, ...] = ()

    @classmethod
    def of(cls, p: Any) -> Holdout:
        """From the fit parameters' ``holdout_every`` and ``holdout_cameras``."""
        return cls(every=int(p.holdout_every), cameras=tuple(p.holdout_cameras))

    @property
    def active(self) -> bool:
        return self.every > 0 or bool(self.cameras)

    def frame_held(self, position: int) -> bool:
        """Whether the frame at ``position`` (its place in scene.json) is held out."""
        return self.every > 0 and (position + 1) % self.every == 0

    def held(self, position: int, camera: str) -> bool:
        """Whether the image of ``camera`` at frame ``position`` is held out."""
        return camera in self.cameras or self.frame_held(position)

    def trained(self, position: int, camera: str) -> bool:
        return not self.held(position, camera)

    def check(self, scene) -> None:
        """Refuse held-out cameras the scene does not have (a typo would silently hold out none)."""
        from paradrive.errors import SceneError

        unknown = [c for c in self.cameras if c not in scene.cameras]
        if unknown:
            raise SceneError(f"fit: holdout_cameras {unknown} are not in the scene (has "
                             f"{list(scene.cameras)})", scene_id=scene.scene_id,
                             fix="fix the 'holdout_cameras' parameter of the fit stage")

    def describe(self) -> dict:
        return {"every": self.every, "cameras": list(self.cameras)}


def knn_scales(points: torch.Tensor, k: int = 3, chunk: int = 1024,
               min_scale: float = 1e-3, max_scale: float | None = None) -> torch.Tensor:
    """Isotropic standard deviations (N, 3) from the RMS distance to the k nearest neighbours
    (the 3DGS initialisation). points: (N, 3)."""
    n = points.shape[0]
    p = points.float()
    out = torch.empty(n)
    kk = min(k + 1, n)
    for i in range(0, n, chunk):
        d2 = torch.cdist(p[i:i + chunk], p).pow(2)
        vals = torch.topk(d2, kk, dim=1, largest=False).values[:, 1:]
        out[i:i + chunk] = vals.mean(1).sqrt() if vals.shape[1] else torch.ones(len(vals))
    out = out.clamp_min(min_scale)
    if max_scale is not None:
        out = out.clamp_max(max_scale)
    return out[:, None].expand(n, 3).contiguous()


def project(points: torch.Tensor, view: View) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points (N, 3) -> pixel coords (N, 2), depth (N,), in-frame mask (N,)."""
    w2c = torch.linalg.inv(view.c2w)
    pc = points.double() @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    K = view.K.double()
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    ok = (z > 0.05) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
    return torch.stack([u, v], 1).float(), z.float(), ok


def colours_from_views(points: torch.Tensor, views: Sequence[View], default: float = 0.5,
                       skip_sky: bool = True,
                       poses: Sequence[np.ndarray] | None = None) -> torch.Tensor:
    """Colour (N, 3) of each point from the first view (in the given order) that sees it
    (nearest pixel; occlusion ignored). Points no view sees get ``default`` grey.

    poses: None (``points`` in the world), or per view the (4, 4) pose that takes ``points``
    into the world at that view's moment (an actor's box2world for points in its box frame).
    """
    n = points.shape[0]
    rgb = torch.full((n, 3), float(default))
    todo = torch.ones(n, dtype=torch.bool)
    for i, view in enumerate(views):
        if not todo.any():
            break
        idx = torch.nonzero(todo).squeeze(1)
        world = points[idx]
        if poses is not None:
            pose = torch.from_numpy(np.asarray(poses[i])).float()
            world = world @ pose[:3, :3].T + pose[:3, 3]
        uv, _, ok = project(world, view)
        if not ok.any():
            continue
        idx, uv = idx[ok], uv[ok]
        x = uv[:, 0].long().clamp(0, view.width - 1)
        y = uv[:, 1].long().clamp(0, view.height - 1)
        if skip_sky and view.sky is not None:
            keep = ~view.sky[y, x]
            idx, x, y = idx[keep], x[keep], y[keep]
        rgb[idx] = view.image[y, x].float() / 255.0
        todo[idx] = False
    return rgb


def lidar_points_init(points: np.ndarray, views: Sequence[View], *, voxel: float, max_points: int,
                      generator: torch.Generator, nb_neighbors: int = 20,
                      std_ratio: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """LiDAR points (M, 3) -> (means (N, 3), rgb (N, 3)).

    open3d voxel down-sampling and statistical outlier removal, then at most ``max_points``
    drawn with ``generator``; colours from the first views that see each point.
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if voxel > 0:
        pcd = pcd.voxel_down_sample(voxel)
    if len(pcd.points) > nb_neighbors + 1:
        pcd, _ = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    pts = np.asarray(pcd.points, np.float64)
    # open3d's hash-map order is not guaranteed: sort so that the init is reproducible.
    pts = pts[np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0]))]
    t = torch.from_numpy(pts).float()
    if len(t) > max_points:
        keep = torch.randperm(len(t), generator=generator)[:max_points].sort().values
        t = t[keep]
    return t, colours_from_views(t, views)


def _blur(img: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(H, W, 3) -> box-blurred (3, H, W)."""
    x = img.permute(2, 0, 1)[None]
    return F.avg_pool2d(F.pad(x, (k // 2,) * 4, mode="replicate"), k, stride=1)[0]


def _sample(img_chw: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear sample (3, H, W) at pixel coords (..., 2) -> (..., 3)."""
    h, w = img_chw.shape[1:]
    g = torch.stack([(uv[..., 0] + 0.0) / w * 2 - 1, (uv[..., 1] + 0.0) / h * 2 - 1], -1)
    shape = g.shape[:-1]
    out = F.grid_sample(img_chw[None], g.reshape(1, -1, 1, 2), mode="bilinear",
                        padding_mode="border", align_corners=False)
    return out[0, :, :, 0].T.reshape(shape + (3,))


def _sweep(o: torch.Tensor, dirs_w: torch.Tensor, d: torch.Tensor, ref: torch.Tensor,
           near: list[View], blurred: list[torch.Tensor], depth: torch.Tensor,
           on_road: torch.Tensor | None, ground_margin: float | None) -> torch.Tensor:
    """The plane sweep: of the candidate depths ``d`` (P, D) along each ray, the one whose colour
    in the ``near`` views best matches ``ref``; ``depth`` where no view sees a ray. With
    ``on_road`` (the last candidate is the road) the road wins within ``ground_margin``."""
    per_view, nd = d.shape
    pts = o + dirs_w[:, None, :] * d[:, :, None]       # (P, D, 3)
    cost = torch.zeros(per_view, nd)
    seen = torch.zeros(per_view, nd)
    for view, image in zip(near, blurred):
        uv, _, ok = project(pts.reshape(-1, 3), view)
        col = _sample(image, uv)
        diff = (col - ref.repeat_interleave(nd, 0)).abs().mean(1)
        cost += torch.where(ok, diff, torch.zeros_like(diff)).reshape(per_view, -1)
        seen += ok.float().reshape(per_view, -1)
    score = torch.where(seen > 0, cost / seen.clamp_min(1), torch.full_like(cost, 1e3))
    best = score.argmin(1)
    if on_road is not None and ground_margin is not None:
        best_score = score.gather(1, best[:, None])[:, 0]
        road_ok = on_road & (score[:, -1] <= best_score + ground_margin)
        best = torch.where(road_ok, torch.full_like(best, nd - 1), best)
    checked = seen.gather(1, best[:, None])[:, 0] > 0
    return torch.where(checked, d.gather(1, best[:, None])[:, 0], depth)


def frustum_points_init(views: Sequence[View], *, n_points: int, depth_min: float, depth_max: float,
                        generator: torch.Generator, depth_candidates: int = 32,
                        neighbours: int = 4,
                        ground_margin: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """LiDAR-free initialisation: points along pixel rays of the training views.

    For each view, ``n_points / len(views)`` non-sky pixels are drawn; along each ray
    ``depth_candidates`` depths uniform in inverse depth over [depth_min, depth_max] are tested
    by photo-consistency (colour difference against up to ``neighbours`` other views of the same
    camera, nearest in time) and the best one is kept (a small plane sweep). Where the view knows
    the road height (``View.ground_z``), the ray's hit on the road plane is one more candidate.
    Rays no neighbour can check keep a random depth. Colour is the pixel's.

    ground_margin: None, or the road prior: a ray that meets the road plane in range takes it
    when its colour difference there is within ``ground_margin`` (mean absolute, colours in
    [0, 1]) of the best candidate's, and when no neighbour can check it. The road is textureless
    and has no best depth of its own; without the prior such rays pick a near candidate at
    random, and those points become floaters in front of the camera.

    Returns means (N, 3), rgb (N, 3).
    """
    if depth_max <= depth_min:
        raise ValueError(f"depth range [{depth_min}, {depth_max}] is empty")
    by_cam: dict[str, list[int]] = {}
    for i, v in enumerate(views):
        by_cam.setdefault(v.camera, []).append(i)
    blurred = [_blur(v.rgb()) for v in views]
    per_view = max(1, math.ceil(n_points / max(len(views), 1)))
    inv = torch.linspace(1.0 / depth_min, 1.0 / depth_max, depth_candidates)
    means, colours = [], []
    for i, view in enumerate(views):
        h, w = view.height, view.width
        allowed = torch.ones(h * w, dtype=torch.bool) if view.sky is None else ~view.sky.reshape(-1)
        cand = torch.nonzero(allowed).squeeze(1)
        if len(cand) == 0:
            continue
        pick = cand[torch.randint(len(cand), (per_view,), generator=generator)]
        jitter = torch.rand(per_view, 2, generator=generator)
        px = (pick % w).float() + jitter[:, 0]
        py = (pick // w).float() + jitter[:, 1]
        K = view.K.double()
        dirs_c = torch.stack([(px.double() - K[0, 2]) / K[0, 0], (py.double() - K[1, 2]) / K[1, 1],
                              torch.ones(per_view, dtype=torch.float64)], 1)
        R = view.c2w[:3, :3].double()
        o = view.c2w[:3, 3].double()
        dirs_w = dirs_c @ R.T                                  # (P, 3), z-depth units
        # random inverse depth for rays nobody can check
        u = torch.rand(per_view, generator=generator).double()
        depth = 1.0 / (1.0 / depth_min + u * (1.0 / depth_max - 1.0 / depth_min))
        on_road = torch.zeros(per_view, dtype=torch.bool)
        if view.ground_z is not None:
            # driving prior: the road plane under the vehicle, hit at z-depth tg
            dz = dirs_w[:, 2]
            tg = (float(view.ground_z) - o[2]) / torch.where(dz.abs() > 1e-9, dz, torch.full_like(dz, -1e-9))
            on_road = (tg > depth_min) & (tg < depth_max)
            tg = torch.where(on_road, tg, torch.full_like(tg, depth_min))
            if ground_margin is not None:
                depth = torch.where(on_road, tg, depth)
        ref = _sample(blurred[i], torch.stack([px, py], 1))    # (P, 3)
        siblings = by_cam[view.camera]
        pos = siblings.index(i)
        near = sorted(siblings, key=lambda j: (abs(siblings.index(j) - pos), j))[1:neighbours + 1]
        if near:
            d = (1.0 / inv.double())[None].expand(per_view, -1)  # (P, D)
            if view.ground_z is not None:
                d = torch.cat([d, tg[:, None]], 1)
            road = on_road if ground_margin is not None and view.ground_z is not None else None
            depth = _sweep(o, dirs_w, d, ref, [views[j] for j in near], [blurred[j] for j in near],
                           depth, road, ground_margin)
        means.append((o + dirs_w * depth[:, None]).float())
        colours.append(view.image[py.long().clamp(0, h - 1), px.long().clamp(0, w - 1)].float() / 255.0)
    if not means:
        raise ValueError("no non-sky pixels to initialise from")
    m, c = torch.cat(means), torch.cat(colours)
    return m[:n_points], c[:n_points]


def sky_dome(views: Sequence[View], *, n_points: int, radius: float, center: torch.Tensor,
             min_elevation_deg: float = -15.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussians on a sphere of ``radius`` around ``center`` (world z up) above
    ``min_elevation_deg``: they hold the sky (and anything farther than the scene) so the
    sky is not explained by floaters. Fibonacci-sphere placement (deterministic). Colours from the
    sky pixels of the views that see them (any pixel when a scene has no sky masks).
    Returns means (N, 3), rgb (N, 3), scales (N, 3).
    """
    zmin = math.sin(math.radians(min_elevation_deg))
    frac = (1.0 - zmin) / 2.0                     # fraction of the sphere's area kept
    total = max(int(math.ceil(n_points / frac)), 1)
    i = torch.arange(total, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / total
    r = torch.sqrt((1.0 - z * z).clamp_min(0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 1)
    dirs = dirs[z >= zmin][:n_points]
    means = (center.double() + radius * dirs).float()
    spacing = radius * math.sqrt(4.0 * math.pi * frac / max(len(dirs), 1))
    scales = torch.full((len(dirs), 3), 0.7 * spacing)
    rgb = colours_from_views(means, views, default=0.7, skip_sky=False)
    if any(v.sky is not None for v in views):
        # prefer sky pixels: recolour from views where the projected pixel is sky
        rgb_sky = torch.full_like(rgb, -1.0)
        todo = torch.ones(len(means), dtype=torch.bool)
        for view in views:
            if view.sky is None or not todo.any():
                continue
            idx = torch.nonzero(todo).squeeze(1)
            uv, _, ok = project(means[idx], view)
            idx, uv = idx[ok], uv[ok]
            x = uv[:, 0].long().clamp(0, view.width - 1)
            y = uv[:, 1].long().clamp(0, view.height - 1)
            s = view.sky[y, x]
            rgb_sky[idx[s]] = view.image[y[s], x[s]].float() / 255.0
            todo[idx[s]] = False
        mean_sky = rgb_sky[~todo].mean(0) if (~todo).any() else rgb.mean(0)
        rgb = torch.where(todo[:, None], mean_sky.expand_as(rgb), rgb_sky)
    return means, rgb, scales
