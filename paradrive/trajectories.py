"""Pictures of one scene's camera paths in a published build (``paradrive inspect --sheet``).

* :func:`trajectories_picture`: the plan, from above (matplotlib): the recorded path (black) and
  the shifted ones (blue to the left, red to the right, darker further out) on equal-aspect axes
  fitted to the paths with a margin, the LiDAR and the actors' tracks underneath, the legend
  below the plot. A drive far longer than the offsets are wide widens the view sideways to at
  most :data:`MAX_ASPECT`, so the picture never becomes a thin band.
* :func:`rig_picture`: the rig in 3D at one frame (pyvista, off-screen): the recorded camera's
  frustum and its shifted copies, each keeping the camera's orientation, over the LiDAR, with
  the paths leading up to them.

Positions come from the manifest (``target_c2w`` and ``target_c2w @ rel_pose``); LiDAR and actors
from the scene folder when it is reachable (``data_dir/scenes/<id>`` or the folder index.json
records). Both pictures are written to a temporary name and renamed into place; the plan's PNG
carries where its plot and its legend lie (``plot_box``, ``legend_box``: left, top, right,
bottom in pixels), for whoever checks or crops it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from paradrive.errors import ParaDriveError
from paradrive.pairs import read_index, read_pairs
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import IndexRecord
from paradrive.streams import format_offset

__all__ = ["ScenePaths", "scene_paths", "trajectories_picture", "rig_picture", "ACTOR_COLOURS"]

MAX_ASPECT = 4.0       # the plan is at most this many times wider than high
MARGIN = 0.05          # of the paths' larger span, on every side of the plan ...
MIN_MARGIN_M = 2.0     # ... and at least this much
PLAN_WIDTH_IN = 12.0   # the plan's figure width; its height follows the data ...
PLAN_HEIGHT_IN = 10.0  # ... up to this plot height (a window taller than wide narrows the figure)
DPI = 100
ACTOR_COLOURS = {"vehicle": (0.95, 0.55, 0.0), "pedestrian": (0.1, 0.6, 0.2),
                 "cyclist": (0.55, 0.2, 0.7), "other": (0.4, 0.4, 0.4)}


@dataclass
class CameraPath:
    """One clip's recorded camera path and its copy shifted by ``offset_m`` (world, metres)."""

    clip: str
    offset_m: float
    recorded: np.ndarray     # (T, 4, 4) camera-to-world
    source: np.ndarray       # (T, 4, 4)


@dataclass
class ScenePaths:
    """What both pictures draw of one scene."""

    scene_id: str
    paths: list[CameraPath]
    intrinsics: tuple[float, float, float, float]
    size: tuple[int, int]                              # width, height of the clips
    folders: list[SceneLayout] = field(default_factory=list)

    @property
    def offsets(self) -> list[float]:
        return sorted({p.offset_m for p in self.paths})

    def colour(self, offset_m: float) -> tuple[float, float, float]:
        """Left (+) blue, right (-) red, darker further out."""
        a = abs(offset_m) / max(1e-6, max(abs(d) for d in self.offsets))
        if offset_m > 0:
            return (0.55 - 0.45 * a, 0.65 - 0.45 * a, 1.0)
        return (1.0, 0.6 - 0.45 * a, 0.55 - 0.45 * a)

    def positions(self) -> np.ndarray:
        """Every camera position drawn, (N, 3)."""
        return np.concatenate([np.concatenate([p.recorded[:, :3, 3], p.source[:, :3, 3]])
                               for p in self.paths])

    def tracks(self) -> list[tuple[str, np.ndarray]]:
        from paradrive.actors import read_tracks

        return next((t for t in (read_tracks(f.root) for f in self.folders) if t), [])

    def lidar(self, max_points: int = 60_000) -> np.ndarray | None:
        for layout in self.folders:
            folder = layout.lidar_dir
            files = sorted(folder.glob("*.npy")) if folder.is_dir() else []
            if files:
                files = files[:: max(1, len(files) // 20)]
                pts = np.concatenate([np.load(f).astype(np.float32).reshape(-1, 3) for f in files])
                if len(pts) > max_points:
                    pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
                return pts
        return None


def _scene_folders(index: IndexRecord, scene_id: str, data_dir) -> list[SceneLayout]:
    """Where the scene's folder may be: ``data_dir/scenes/<id>``, then what index.json records."""
    candidates = []
    if data_dir is not None:
        candidates.append(SceneLayout.of(data_dir, scene_id))
    for s in index.scenes:
        if s.scene_id == scene_id and s.scene_dir:
            candidates.append(SceneLayout(Path(s.scene_dir)))
    return candidates


def scene_paths(build_dir: str | Path, scene_id: str | None = None,
                data_dir: str | Path | None = None) -> ScenePaths:
    """The recorded and shifted paths of ``scene_id`` (default: the build's first scene), one
    per clip and offset (the pairs of the lowest condition checkpoint)."""
    build_dir = Path(build_dir)
    index = read_index(build_dir)
    table = read_pairs(build_dir, ["scene_id", "clip", "offset_m", "condition_iteration", "rel_pose",
                                   "target_c2w", "intrinsics", "width", "height"], index)
    sids = table.column("scene_id").to_pylist()
    scene_id = scene_id or sids[0]
    rows = table.filter(np.array([s == scene_id for s in sids])).to_pylist()
    if not rows:
        raise ParaDriveError(f"{build_dir}: no pairs of scene {scene_id}")
    first_it = min(r["condition_iteration"] for r in rows)
    paths = []
    for r in sorted((r for r in rows if r["condition_iteration"] == first_it),
                    key=lambda r: (r["clip"], r["offset_m"])):
        c2w = np.asarray(r["target_c2w"], np.float64).reshape(-1, 4, 4)
        rel = np.asarray(r["rel_pose"], np.float64).reshape(-1, 4, 4)
        paths.append(CameraPath(r["clip"], float(r["offset_m"]), c2w, c2w @ rel))
    fx, fy, cx, cy = (float(v) for v in rows[0]["intrinsics"])
    return ScenePaths(scene_id, paths, (fx, fy, cx, cy), (int(rows[0]["width"]), int(rows[0]["height"])),
                      _scene_folders(index, scene_id, data_dir))


def _publish(out: Path, save) -> Path:
    """``save(temporary path)``, then rename into place."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp-{os.getpid()}{out.suffix}")
    try:
        save(tmp)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


# --------------------------------------------------------------------------- the plan

def plan_window(points_xy: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """(x range, y range) around ``points_xy``: a margin on every side, then the narrower side
    widened until the window is at most :data:`MAX_ASPECT` times longer than wide."""
    lo, hi = points_xy.min(axis=0), points_xy.max(axis=0)
    margin = max(MARGIN * float((hi - lo).max()), MIN_MARGIN_M)
    lo, hi = lo - margin, hi + margin
    span = hi - lo
    long = int(np.argmax(span))
    short = 1 - long
    need = span[long] / MAX_ASPECT
    if span[short] < need:
        centre = 0.5 * (lo[short] + hi[short])
        lo[short], hi[short] = centre - need / 2, centre + need / 2
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


def _draw_plan(ax, scene: ScenePaths, window) -> None:
    (x0, x1), (y0, y1) = window
    points = scene.lidar()
    if points is not None:
        inside = (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)
        ax.scatter(points[inside, 0], points[inside, 1], s=0.3, c=[(0.72, 0.72, 0.72)], linewidths=0,
                   rasterized=True, zorder=0, label=f"LiDAR ({len(points)} points)")
    labelled: set[str] = set()
    for cls, centres in scene.tracks():
        inside = ((centres[:, 0] >= x0) & (centres[:, 0] <= x1) & (centres[:, 1] >= y0)
                  & (centres[:, 1] <= y1))
        if not inside.any():
            continue
        centres = np.where(inside[:, None], centres, np.nan)  # the window frames the paths only
        centres = centres[np.argmax(inside):]
        label = None if cls in labelled else f"{cls} tracks"
        labelled.add(cls)
        if np.nanmax(np.nanmax(centres, axis=0) - np.nanmin(centres, axis=0)) > 1e-3:
            ax.plot(centres[:, 0], centres[:, 1], color=ACTOR_COLOURS[cls], lw=2.0, zorder=1, label=label)
        else:  # a parked car: one dot
            ax.plot(centres[:1, 0], centres[:1, 1], "s", color=ACTOR_COLOURS[cls], ms=3, zorder=1,
                    label=label)
    drawn: set[float] = set()
    for path in scene.paths:
        src = path.source[:, :3, 3]
        ax.plot(src[:, 0], src[:, 1], color=scene.colour(path.offset_m), lw=1.6, zorder=2,
                label=None if path.offset_m in drawn else f"source {format_offset(path.offset_m)}")
        drawn.add(path.offset_m)
    for i, path in enumerate(p for p in scene.paths if p.offset_m == scene.offsets[0]):
        rec = path.recorded[:, :3, 3]
        ax.plot(rec[:, 0], rec[:, 1], color="black", lw=2.4, zorder=3,
                label="recorded (target, condition)" if i == 0 else None)
        ax.plot(rec[:1, 0], rec[:1, 1], "o", color="black", ms=5, zorder=4,
                label=f"clip start ({', '.join(sorted({p.clip for p in scene.paths}))})" if i == 0 else None)


def _layout(fig, ax, legend, aspect: float, margins: list[float]) -> None:
    """Place the plot with ``margins`` (left, right, top, bottom inches around it, the legend
    below the bottom one) and size the figure so the plot has the window's ``aspect``."""
    left, right, top, bottom = margins
    legend_in = legend.get_window_extent().height / DPI + 0.1
    fig_w = fig.get_figwidth()
    width = min(fig_w - left - right, PLAN_HEIGHT_IN * aspect)
    height = width / aspect
    fig_h = top + height + bottom + legend_in
    fig.set_figheight(fig_h)
    x = left + 0.5 * (fig_w - left - right - width)
    ax.set_position([x / fig_w, (bottom + legend_in) / fig_h, width / fig_w, height / fig_h])
    legend.set_bbox_to_anchor((0.5, 0.05 / fig_h), transform=fig.transFigure)


def trajectories_picture(build_dir: str | Path, out: str | Path, *, scene_id: str | None = None,
                         data_dir: str | Path | None = None) -> Path:
    """The plan of one scene's camera paths, from above (see the module doc); returns ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PathCollection

    scene = scene_paths(build_dir, scene_id, data_dir)
    window = plan_window(scene.positions()[:, :2])
    (x0, x1), (y0, y1) = window
    aspect = (x1 - x0) / (y1 - y0)
    fig_w = max(min(PLAN_WIDTH_IN, PLAN_HEIGHT_IN * aspect + 0.8), 6.0)
    fig = plt.figure(figsize=(fig_w, fig_w / aspect), dpi=DPI)
    try:
        ax = fig.add_axes((0.1, 0.1, 0.8, 0.8))
        _draw_plan(ax, scene, window)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(True, color=(0.88, 0.88, 0.88), lw=0.6, zorder=-1)
        ax.set_title(f"{scene.scene_id}: camera paths from above (scene world; + offset = left)",
                     fontsize=10)
        handles, labels = ax.get_legend_handles_labels()
        legend = fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6 if fig_w > 10 else 3),
                            fontsize=8, frameon=False)
        for handle in legend.legend_handles:  # LiDAR's dots, big enough to see in the legend
            if isinstance(handle, PathCollection):
                handle.set_sizes([12.0])
        margins = [0.5, 0.2, 0.3, 0.3]     # inches; grown below to what the labels need
        for _ in range(2):
            _layout(fig, ax, legend, aspect, margins)
            fig.canvas.draw()
            plot, whole = ax.get_window_extent(), ax.get_tightbbox()
            assert whole is not None  # the axes is drawn
            need = [plot.x0 - whole.x0, whole.x1 - plot.x1, whole.y1 - plot.y1, plot.y0 - whole.y0]
            margins = [max(m, n / DPI + 0.1) for m, n in zip(margins, need)]
        height = fig.bbox.height
        boxes = {"plot_box": ax.get_window_extent(), "legend_box": legend.get_window_extent()}
        meta = {k: json.dumps([round(b.x0), round(height - b.y1), round(b.x1), round(height - b.y0)])
                for k, b in boxes.items()}
        return _publish(Path(out), lambda tmp: fig.savefig(tmp, format="png", dpi=DPI, metadata=meta))
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- the rig in 3D

def _frustum(c2w: np.ndarray, intrinsics, size, depth: float) -> np.ndarray:
    """The 5 world points of a camera's frustum drawn ``depth`` metres deep: centre, 4 corners."""
    fx, fy, cx, cy = intrinsics
    w, h = size
    corners = np.array([[(u - cx) / fx * depth, (v - cy) / fy * depth, depth]
                        for u, v in ((0, 0), (w, 0), (w, h), (0, h))])
    local = np.vstack([np.zeros(3), corners])
    return local @ c2w[:3, :3].T + c2w[:3, 3]


def _add_frustum(plotter, pv, c2w, scene: ScenePaths, colour, depth: float, width: float,
                 label: str | None) -> None:
    pts = _frustum(c2w, scene.intrinsics, scene.size, depth)
    lines = [2, 0, 1, 2, 0, 2, 2, 0, 3, 2, 0, 4, 2, 1, 2, 2, 2, 3, 2, 3, 4, 2, 4, 1]
    plotter.add_mesh(pv.PolyData(pts, lines=lines), color=colour, line_width=width, label=label)
    plotter.add_mesh(pv.PolyData(pts[1:], faces=[4, 0, 1, 2, 3]), color=colour, opacity=0.25)


def rig_picture(build_dir: str | Path, out: str | Path, *, scene_id: str | None = None,
                data_dir: str | Path | None = None, size: tuple[int, int] = (1200, 700)) -> Path:
    """The recorded camera and its shifted copies in 3D at the middle frame of the first clip,
    seen from behind and above (pyvista, off-screen); returns ``out``."""
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    if not os.environ.get("DISPLAY"):
        # No X server: render with OSMesa (installed by the setup) instead of failing over from X.
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkOSOpenGLRenderWindow")
    import pyvista as pv

    scene = scene_paths(build_dir, scene_id, data_dir)
    first = [p for p in scene.paths if p.clip == scene.paths[0].clip]
    frame = len(first[0].recorded) // 2
    rec = first[0].recorded
    spread = max(abs(d) for d in scene.offsets)
    depth = max(0.2 * spread, 0.4)
    plotter: Any = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        plotter.set_background("white")
        centre = rec[frame, :3, 3]
        points = scene.lidar()
        if points is not None:
            near = np.linalg.norm(points[:, :2] - centre[:2], axis=1) < 6 * spread + 10
            if near.any():
                plotter.add_points(points[near], color=(0.65, 0.65, 0.65), point_size=2,
                                   render_points_as_spheres=False)
        plotter.add_mesh(pv.lines_from_points(rec[: frame + 1, :3, 3]), color="black", line_width=3)
        _add_frustum(plotter, pv, rec[frame], scene, (0.0, 0.0, 0.0), depth, 4, "recorded camera")
        for path in first:
            colour = scene.colour(path.offset_m)
            plotter.add_mesh(pv.lines_from_points(path.source[: frame + 1, :3, 3]), color=colour,
                             line_width=2)
            _add_frustum(plotter, pv, path.source[frame], scene, colour, depth, 3,
                         f"shifted {format_offset(path.offset_m)}")
        plotter.add_legend(bcolor="white", size=(0.15, 0.36), loc="upper right", face="line")
        plotter.add_text(f"{scene.scene_id}: the rig at frame {frame} of clip {first[0].clip}, "
                         f"cameras shifted sideways keeping their orientation",
                         font_size=9, color="black", position="upper_left")
        # from behind the rig (against the camera's forward axis), above it, looking at the rig
        forward = rec[frame, :3, 2].copy()
        forward[2] = 0.0
        forward /= max(float(np.linalg.norm(forward)), 1e-9)
        plotter.camera.focal_point = centre + forward * (0.6 * spread)
        plotter.camera.position = centre - forward * (1.2 * spread + 2) + np.array([0, 0, 1.1 * spread + 2])
        plotter.camera.up = (0.0, 0.0, 1.0)
        plotter.camera.view_angle = 50.0
        return _publish(Path(out), lambda tmp: plotter.screenshot(str(tmp)))
    finally:
        plotter.close()
