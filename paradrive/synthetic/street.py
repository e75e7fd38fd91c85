"""The procedural street: layout from a seed, the camera rig, the trajectory, and textures.

Road-aligned coordinates (s along the centreline, l to the left, z up) are those of
``raycast.RoadArc``; the ego drives along l = 0, the centre lane of three, so shifts of +-4 m
stay on asphalt. Lateral profile (both sides, from the centre out):

    |l| < 1.5 lane_w           driving lanes (dashed dividers at +-lane_w/2, solid edge lines)
    edge .. kerb_l             parking lane with parked cars
    kerb_l .. facade line      raised sidewalk (kerb height 0.15 m) with lamp posts and trees
    facade line ..             buildings (front row with gaps, a taller back row behind)
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from paradrive.actors import Actor
from paradrive.geometry import rotation_about
from paradrive.scene import Camera
from paradrive.synthetic import raycast as rc
from paradrive.synthetic import traffic
from paradrive.synthetic.limits import MAX_TRAVEL_M, along, check_values

# box / cylinder / sphere materials
FACADE, CAR, CABIN, WHEEL, METAL, LAMP, TRUNK, FOLIAGE, PERSON = range(9)

KERB_H = 0.15
# shading groups (sorted order: sky first)
_G_SKY, _G_GROUND, _G_CYL, _G_SPH, _G_BOX = 0, 1, 8, 9, 16


def _group_kind(group: int) -> int:
    if group >= _G_BOX:
        return rc.BOX
    if group == _G_CYL:
        return rc.CYLINDER
    if group == _G_SPH:
        return rc.SPHERE
    return rc.GROUND
# the front three as in Waymo; with the back three, a six-camera rig as in nuScenes
CAMERA_NAMES = ("front", "front_left", "front_right", "back_left", "back_right", "back")
LIDAR_HEIGHT = 1.95
LIDAR_BEAMS = 32
LIDAR_AZIMUTHS = 512
LIDAR_ELEVATION_DEG = (-25.0, 5.0)
LIDAR_MAX_RANGE = 75.0

_FACADE_COLOURS = np.array([
    (0.56, 0.28, 0.21), (0.63, 0.36, 0.26), (0.46, 0.23, 0.19),   # bricks
    (0.82, 0.75, 0.60), (0.90, 0.86, 0.75), (0.60, 0.60, 0.62), (0.60, 0.70, 0.78),
    (0.80, 0.62, 0.36), (0.36, 0.34, 0.33), (0.56, 0.63, 0.55), (0.78, 0.55, 0.50),
])
_CAR_COLOURS = np.array([
    (0.88, 0.88, 0.86), (0.62, 0.63, 0.65), (0.10, 0.10, 0.11), (0.62, 0.08, 0.07),
    (0.10, 0.22, 0.50), (0.12, 0.28, 0.18), (0.85, 0.68, 0.10), (0.35, 0.36, 0.38),
])


# The rig's cameras are the canonical scene's pinhole cameras (OpenCV axes, cam2ego to ego).
CameraSpec = Camera


def camera_spec(name: str, width: int, height: int, hfov_deg: float = 70.0,
                pitch_deg: float = 3.0) -> CameraSpec:
    """The rig's camera ``name``: front (1.5 m ahead of the ego origin, 1.6 m up, pitched down),
    front_left / front_right yawed +-45 deg, back_left / back_right +-110 deg, back 180 deg."""
    yaw, pos = {"front": (0.0, (1.5, 0.0, 1.6)),
                "front_left": (np.pi / 4, (1.3, 0.5, 1.6)),
                "front_right": (-np.pi / 4, (1.3, -0.5, 1.6)),
                "back_left": (np.deg2rad(110.0), (0.9, 0.5, 1.6)),
                "back_right": (np.deg2rad(-110.0), (0.9, -0.5, 1.6)),
                "back": (np.pi, (-0.5, 0.0, 1.6))}[name]
    p = np.deg2rad(pitch_deg)
    # columns: camera x (right), y (down), z (forward) in ego axes, pitched down by p
    rot = np.array([[0.0, -np.sin(p), np.cos(p)],
                    [-1.0, 0.0, 0.0],
                    [0.0, -np.cos(p), -np.sin(p)]])
    cam2ego = np.eye(4)
    cam2ego[:3, :3] = rotation_about("z", yaw) @ rot
    cam2ego[:3, 3] = pos
    f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    return CameraSpec(name, int(width), int(height), float(f), float(f), 0.5 * width, 0.5 * height,
                      cam2ego)


# ---------------------------------------------------------------------------------------------
# the street's parameters: what each may be


def camera_names(cameras) -> tuple[str, ...]:
    """The rig's cameras from a tuple or a comma-separated string; ValueError for an unknown
    one or none."""
    if isinstance(cameras, str):
        cameras = tuple(c.strip() for c in cameras.split(",") if c.strip())
    cameras = tuple(cameras)
    unknown = [c for c in cameras if c not in CAMERA_NAMES]
    if unknown or not cameras:
        raise ValueError(f"synthetic street: unknown camera(s) {unknown or cameras!r}; "
                         f"use any of {', '.join(CAMERA_NAMES)}")
    return cameras


def defaults() -> dict[str, Any]:
    """SyntheticStreet's own defaults, read from its signature (where they are defined)."""
    import inspect

    return {name: p.default for name, p in inspect.signature(SyntheticStreet).parameters.items()
            if p.default is not inspect.Parameter.empty}


# the road laid out behind the first frame and ahead of the last one (m)
_BEHIND_M, _AHEAD_M = 40.0, 160.0


def drive(frames: int, speed_mps: float, fps: float, kappa: float) -> tuple[float, float]:
    """The arc lengths ``(s_min, s_max)`` the street is laid out over; ValueError for a drive
    longer than :data:`MAX_TRAVEL_M` or one that turns more than 160 degrees."""
    travel = speed_mps * (frames - 1) / fps
    if not abs(travel) <= MAX_TRAVEL_M:
        raise ValueError(f"synthetic street: {frames} frames at {speed_mps} m/s and {fps} frames "
                         f"a second drive {travel:.0f} m, over the {MAX_TRAVEL_M:.0f} m a street "
                         f"may be; use fewer frames or a lower speed")
    s_min, s_max = min(0.0, travel) - _BEHIND_M, max(0.0, travel) + _AHEAD_M
    if kappa != 0.0 and max(abs(s_min), abs(s_max)) * abs(kappa) > 0.9 * np.pi:
        raise ValueError(f"synthetic street: {frames} frames at {speed_mps} m/s on "
                         f"curvature {kappa} turn more than 160 deg; use fewer frames "
                         "or a smaller curvature")
    return s_min, s_max


# ---------------------------------------------------------------------------------------------
# layout


@dataclass
class Layout:
    """The street's objects and look, all derived from the seed."""

    lane_w: float
    edge_l: float
    kerb_l: float
    facade_l: tuple[float, float]  # left, right (positive distances)
    boxes: np.ndarray      # (nb, 6) s0, s1, l0, l1, z0, z1
    box_mat: np.ndarray    # (nb,) material
    box_rgb: np.ndarray    # (nb, 3) base colour
    box_rgb2: np.ndarray   # (nb, 3) second colour (window frames)
    box_par: np.ndarray    # (nb, 8) facade: style, floor_h, spacing, win_w, win_h, sill, shop; car: facing
    cylinders: np.ndarray  # (nc, 5) cx, cy, r, z0, z1 (world)
    cyl_mat: np.ndarray
    cyl_rgb: np.ndarray
    spheres: np.ndarray    # (ns, 4) cx, cy, cz, r (world)
    sph_mat: np.ndarray
    sph_rgb: np.ndarray
    asphalt: float
    sun: np.ndarray        # (3,) unit, towards the sun (world)
    zenith: np.ndarray
    horizon: np.ndarray
    movers: list[traffic.Mover] = field(default_factory=list)  # parked cars, then traffic

    def __post_init__(self):
        # float32 copies for texturing (coordinates of a few hundred metres, cm-scale patterns)
        self.tex = {k: getattr(self, k).astype(np.float32)
                    for k in ("boxes", "box_par", "box_rgb", "box_rgb2", "cyl_rgb", "sph_rgb")}
        # texture keys from geometry, not list position: the same object looks the same in a
        # longer street of the same seed

        def key(a, b):
            return np.round(a * 1000).astype(np.int64) * 1000003 + np.round(b * 1000).astype(np.int64)

        self.box_id = key(self.boxes[:, 0], self.boxes[:, 2])
        self.cyl_id = key(self.cylinders[:, 0], self.cylinders[:, 1])
        self.sph_id = key(self.spheres[:, 0], self.spheres[:, 2])


def _car_parts(s: float, length: float, l0: float, l1: float, body_top: float, cab_h: float,
               back_in: float, front_in: float) -> list[tuple[tuple, int]]:
    """(box, material) of a car's body, cabin and two axle blocks, rear end at s."""
    parts = [((s, s + length, l0, l1, 0.28, body_top), CAR),
             ((s + back_in, s + length - front_in, l0 + 0.1, l1 - 0.1, body_top,
               body_top + cab_h), CABIN)]
    for ax in (0.8, length - 0.85):
        parts.append(((s + ax - 0.33, s + ax + 0.33, l0 + 0.03, l1 - 0.03, 0.0, 0.62), WHEEL))
    return parts


def _person_parts(s: float, lc: float, height: float) -> list[tuple[tuple, int]]:
    """(box, part) of a standing person at road (s, lc): legs, torso, head (facing across)."""
    hip, neck = 0.5 * height, 0.84 * height
    return [((s - 0.17, s + 0.17, lc - 0.11, lc + 0.11, 0.0, hip), 0),
            ((s - 0.25, s + 0.25, lc - 0.15, lc + 0.15, hip, neck), 1),
            ((s - 0.1, s + 0.1, lc - 0.11, lc + 0.11, neck, height), 2)]


def build_layout(seed: int, arc: rc.RoadArc, s_min: float, s_max: float, *,
                 ego_speed: float = 0.0) -> Layout:
    """Procedural layout of the street over arc length [s_min, s_max].

    Each category draws from its own stream, placing objects in order along s, so a longer street
    has the same objects at the same places as a shorter one with the same seed. With
    ``ego_speed`` (m/s) > 0 the street has traffic (traffic.py) timed to that ego.
    """
    root = np.random.SeedSequence(int(seed))
    (g_look, g_bl, g_br, g_back, g_cars, g_lamps, g_trees) = [
        {1.0: np.random.default_rng(a), -1.0: np.random.default_rng(b)}
        for a, b in (s.spawn(2) for s in root.spawn(7))]
    builder = _LayoutBuilder(g_look[1.0], arc, s_min, s_max)
    builder.facades({1.0: g_bl[1.0], -1.0: g_br[1.0]})
    builder.back_facades(g_back)
    builder.parked_cars(g_cars)
    lamp_s = builder.lamps(g_lamps)
    builder.trees(g_trees, lamp_s)
    if ego_speed > 0:
        builder.movers += traffic_movers(root.spawn(1)[0], builder.lane_w, builder.kerb_l,
                                         ego_speed, s_min, s_max,
                                         functools.partial(_moving_car, builder.add_box),
                                         functools.partial(_crossing_person, builder.add_box))
    return builder.layout()


def _facade_params(g, back: bool = False):
    ci = g.integers(len(_FACADE_COLOURS))
    colour = _FACADE_COLOURS[ci] + g.uniform(-0.05, 0.05, 3)
    style = float(ci < 3 or g.random() < 0.15)  # 1 = brick, 0 = plaster
    floor_h = g.uniform(3.0, 3.6)
    spacing = g.uniform(2.2, 3.4)
    win_w = spacing * g.uniform(0.38, 0.6)
    win_h = g.uniform(1.2, floor_h - 1.2)
    sill = g.uniform(0.8, floor_h - 0.3 - win_h)
    shop = float((not back) and g.random() < 0.5)
    frame = (0.92, 0.91, 0.88) if g.random() < 0.6 else (0.18, 0.18, 0.2)
    return colour, frame, (style, floor_h, spacing, win_w, win_h, sill, shop)


class _LayoutBuilder:
    """The street's look and the objects added so far (boxes in the order they are added: a
    box's row is its index)."""

    def __init__(self, g_look, arc: rc.RoadArc, s_min: float, s_max: float):
        self.arc, self.s_min, self.s_max = arc, s_min, s_max
        self.lane_w = g_look.uniform(3.3, 3.7)
        self.edge_l = 1.5 * self.lane_w
        self.kerb_l = self.edge_l + g_look.uniform(2.2, 2.6)
        self.facade_l = (self.kerb_l + g_look.uniform(3.0, 5.0), self.kerb_l + g_look.uniform(3.0, 5.0))
        self.asphalt = g_look.uniform(0.26, 0.34)
        az, el = g_look.uniform(0, 2 * np.pi), np.deg2rad(g_look.uniform(30, 55))
        self.sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        self.zenith = np.array([0.30, 0.50, 0.85]) + g_look.uniform(-0.04, 0.04, 3)
        self.horizon = np.array([0.80, 0.86, 0.93]) + g_look.uniform(-0.03, 0.03, 3)
        self.boxes: list = []
        self.mats: list = []
        self.rgb: list = []
        self.rgb2: list = []
        self.par: list = []
        self.cyls: list = []
        self.cmat: list = []
        self.crgb: list = []
        self.sphs: list = []
        self.smat: list = []
        self.srgb: list = []
        self.movers: list[traffic.Mover] = []

    def add_box(self, b, mat, colour, colour2=(0, 0, 0), p=()) -> int:
        self.boxes.append(b)
        self.mats.append(mat)
        self.rgb.append(np.clip(colour, 0, 1))
        self.rgb2.append(np.clip(colour2, 0, 1))
        pp = np.zeros(8)
        pp[:len(p)] = p
        self.par.append(pp)
        return len(self.boxes) - 1

    def facades(self, gens: dict) -> None:
        for side, g in gens.items():
            front = self.facade_l[0] if side > 0 else self.facade_l[1]
            s = self.s_min - g.uniform(0, 10)
            for _ in along(s, self.s_max, 8.0):   # a facade is 8 m wide at least
                if s >= self.s_max:
                    break
                w = g.uniform(8, 26)
                h = [g.uniform(7, 12), g.uniform(12, 20), g.uniform(20, 32)][g.choice(3, p=[.35, .4, .25])]
                depth = g.uniform(9, 16)
                l_in = front + g.uniform(0, 1.2)
                lo, hi = (l_in, l_in + depth) if side > 0 else (-l_in - depth, -l_in)
                colour, frame, p = _facade_params(g)
                self.add_box((s, s + w, lo, hi, KERB_H, h), FACADE, colour, frame, p)
                s += w + (g.uniform(2.5, 8) if g.random() < 0.35 else 0.0)

    def back_facades(self, gens: dict) -> None:
        for side in (1.0, -1.0):
            g = gens[side]
            front = (self.facade_l[0] if side > 0 else self.facade_l[1]) + 18.0
            s = self.s_min - g.uniform(0, 20)
            for _ in along(s, self.s_max, 14.0):
                if s >= self.s_max:
                    break
                w = g.uniform(14, 40)
                h = g.uniform(16, 45)
                l_in = front + g.uniform(0, 6)
                lo, hi = (l_in, l_in + 12) if side > 0 else (-l_in - 12, -l_in)
                colour, frame, p = _facade_params(g, back=True)
                self.add_box((s, s + w, lo, hi, KERB_H, h), FACADE, colour, frame, p)
                s += w + g.uniform(0, 4)

    def parked_cars(self, gens: dict) -> None:
        """Cars in the parking lanes: body, cabin and two axle blocks each."""
        park = 0.5 * (self.edge_l + self.kerb_l)
        for side in (1.0, -1.0):
            g_car = gens[side]
            s = self.s_min + g_car.uniform(0, 6)
            for _ in along(s, self.s_max, 3.9 + 0.8):   # the shortest car and gap
                if s >= self.s_max:
                    break
                length = g_car.uniform(3.9, 4.8)
                width = g_car.uniform(1.72, 1.9)
                lc = side * (park + g_car.uniform(-0.12, 0.12))
                colour = _CAR_COLOURS[g_car.integers(len(_CAR_COLOURS))] + g_car.uniform(-0.03, 0.03, 3)
                facing = 1.0 if g_car.random() < 0.8 else -1.0
                rows, bbox = _add_car(self.add_box, g_car, s, lc, length, width, colour, facing)
                self.movers.append(traffic.Mover(f"parked-{len(self.movers):03d}", "car", rows, bbox,
                                                 yaw=0.0 if facing > 0 else np.pi))
                gap = g_car.uniform(0.8, 6.0) if g_car.random() < 0.8 else g_car.uniform(8, 18)
                s += length + gap

    def lamps(self, gens: dict) -> dict[float, list[float]]:
        """Street lamps by the kerb; their positions along s per side."""
        lamp_s: dict[float, list[float]] = {1.0: [], -1.0: []}
        for side in (1.0, -1.0):
            g_lamp = gens[side]
            s = self.s_min + g_lamp.uniform(0, 20)
            for _ in along(s, self.s_max, 20.0):
                if s >= self.s_max:
                    break
                h = g_lamp.uniform(6.0, 8.0)
                lp = side * (self.kerb_l + 0.6)
                x, y = self.arc.to_world(s, lp)
                self.cyls.append((float(x), float(y), 0.09, 0.0, h))
                self.cmat.append(METAL)
                self.crgb.append((0.33, 0.35, 0.38))
                arm_end = side * (self.kerb_l - 1.2)
                lo, hi = sorted((lp, arm_end))
                self.add_box((s - 0.05, s + 0.05, lo, hi, h - 0.12, h - 0.04), METAL, (0.33, 0.35, 0.38))
                lo, hi = sorted((arm_end, arm_end + side * 0.6))
                self.add_box((s - 0.16, s + 0.16, lo, hi, h - 0.28, h - 0.08), LAMP, (0.95, 0.93, 0.82))
                lamp_s[side].append(s)
                s += g_lamp.uniform(20, 34)
        return lamp_s

    def trees(self, gens: dict, lamp_s: dict[float, list[float]]) -> None:
        for side in (1.0, -1.0):
            g_tree = gens[side]
            s = self.s_min + g_tree.uniform(0, 12)
            near = np.array(lamp_s[side])
            for _ in along(s, self.s_max, 11.0):
                if s >= self.s_max:
                    break
                lt = side * (self.kerb_l + g_tree.uniform(1.3, 1.9))
                r_crown = g_tree.uniform(1.3, 2.2)
                trunk_h = g_tree.uniform(2.6, 3.6)
                tint = np.array([0.20, 0.40, 0.14]) + g_tree.uniform(-0.05, 0.07, 3)
                jitter = g_tree.uniform(-0.6, 0.6, 3)
                step = g_tree.uniform(11, 24)
                if len(near) == 0 or np.min(np.abs(near - s)) > 3.0:
                    self.tree(s, lt, g_tree.uniform(0.12, 0.2), r_crown, trunk_h, tint, jitter)
                s += step

    def tree(self, s: float, lt: float, trunk_r: float, r_crown: float, trunk_h: float, tint,
             jitter) -> None:
        x, y = self.arc.to_world(s, lt)
        x, y = float(x), float(y)
        self.cyls.append((x, y, trunk_r, 0.0, trunk_h + r_crown * 0.5))
        self.cmat.append(TRUNK)
        self.crgb.append((0.33, 0.24, 0.16))
        zc = trunk_h + 0.7 * r_crown
        self.sphs.append((x, y, zc, r_crown))
        self.smat.append(FOLIAGE)
        self.srgb.append(tint)
        self.sphs.append((x + jitter[0], y + jitter[1], zc + 0.5 + 0.3 * jitter[2], 0.75 * r_crown))
        self.smat.append(FOLIAGE)
        self.srgb.append(tint * 1.08)

    def layout(self) -> Layout:
        return Layout(
            lane_w=self.lane_w, edge_l=self.edge_l, kerb_l=self.kerb_l, facade_l=self.facade_l,
            boxes=np.array(self.boxes, np.float64).reshape(-1, 6),
            box_mat=np.array(self.mats, np.int64),
            box_rgb=np.array(self.rgb, np.float64).reshape(-1, 3),
            box_rgb2=np.array(self.rgb2, np.float64).reshape(-1, 3),
            box_par=np.array(self.par, np.float64).reshape(-1, 8),
            cylinders=np.array(self.cyls, np.float64).reshape(-1, 5),
            cyl_mat=np.array(self.cmat, np.int64),
            cyl_rgb=np.array(self.crgb, np.float64).reshape(-1, 3),
            spheres=np.array(self.sphs, np.float64).reshape(-1, 4),
            sph_mat=np.array(self.smat, np.int64),
            sph_rgb=np.array(self.srgb, np.float64).reshape(-1, 3),
            asphalt=float(self.asphalt), sun=self.sun, zenith=np.clip(self.zenith, 0, 1),
            horizon=np.clip(self.horizon, 0, 1), movers=self.movers)


def _moving_car(add_box, g, s: float, lc: float, facing: float):
    """Add a car (rear at s, centred on lc, facing +-s) drawn from g; returns (rows, bbox)."""
    length, width = g.uniform(3.9, 4.8), g.uniform(1.72, 1.9)
    colour = _CAR_COLOURS[g.integers(len(_CAR_COLOURS))] + g.uniform(-0.03, 0.03, 3)
    return _add_car(add_box, g, s, lc, length, width, colour, facing)


def _add_car(add_box, g, s: float, lc: float, length: float, width: float, colour,
             facing: float):
    """Add a car's boxes, its heights and cabin drawn from g; returns (rows, bbox)."""
    body_top = 0.28 + g.uniform(0.62, 0.8)
    cab_h = g.uniform(0.42, 0.58)
    back_in, front_in = g.uniform(0.7, 1.1), g.uniform(1.1, 1.5)
    if facing < 0:
        back_in, front_in = front_in, back_in
    l0, l1 = lc - width / 2, lc + width / 2
    rows = [add_box(box, mat, (0.05, 0.05, 0.05) if mat == WHEEL else colour,
                    p=(facing,) if mat == CAR else ())
            for box, mat in _car_parts(s, length, l0, l1, body_top, cab_h, back_in, front_in)]
    return np.array(rows), np.array([s, s + length, l0, l1, 0.0, body_top + cab_h])


def _crossing_person(add_box, g, s: float, lc: float):
    """Add a person standing at road (s, lc) drawn from g; returns (rows, bbox)."""
    height = g.uniform(1.55, 1.9)
    shirt = traffic.PERSON_COLOURS[g.integers(len(traffic.PERSON_COLOURS))]
    rows = [add_box(box, PERSON, ((0.12, 0.12, 0.16), shirt, (0.78, 0.6, 0.48))[part])
            for box, part in _person_parts(s, lc, height)]
    return np.array(rows), np.array([s - 0.25, s + 0.25, lc - 0.15, lc + 0.15, 0.0, height])


def traffic_movers(seed: np.random.SeedSequence, lane_w: float, kerb_l: float, ego_speed: float,
                   s_min: float, s_max: float, add_car, add_person) -> list[traffic.Mover]:
    """Oncoming cars (left lane), overtaking cars (right lane, faster than the ego) and crossing
    pedestrians, each lane at its own speed and from its own stream (a longer street keeps them)."""
    g_speed, g_on, g_over, g_people = map(np.random.default_rng, seed.spawn(4))
    oncoming = g_speed.uniform(0.8, 1.2) * ego_speed
    overtaking = g_speed.uniform(1.3, 1.6) * ego_speed
    specs = [("car", a) for a in traffic.lane_cars(g_on, lane_w, -1.0, oncoming, s_min, s_max,
                                                   add_car)]
    specs += [("car", a) for a in traffic.lane_cars(g_over, -lane_w, 1.0, overtaking,
                                                    s_min - 20.0, s_max, add_car)]
    specs += [("person", a) for a in traffic.crossing_people(g_people, kerb_l + 1.0, ego_speed,
                                                             s_min, s_max, add_person)]
    return [traffic.Mover(f"{kind}-{i:03d}", kind, *args) for i, (kind, args) in enumerate(specs)]


# ---------------------------------------------------------------------------------------------
# textures: deterministic hashes of quantised coordinates, box-filtered by the pixel footprint


_MIX = (np.int64(0x2545F4914F6CDD1D), np.int64(0x3C6EF372FE94F82B), np.int64(0x1B873593A54FF53A),
        np.int64(0x5851F42D4C957F2D), np.int64(0x14057B7EF767814F))
_H2 = np.uint64(0xBF58476D1CE4E5B9)
_H3 = np.uint64(0x94D049BB133111EB)


def hash01(*keys) -> np.ndarray:
    """Uniform [0, 1) float32 per integer key tuple (broadcast arrays, at most 5 keys)."""
    with np.errstate(over="ignore"):  # wrapping is the point
        acc = np.asarray(0, np.int64)
        for k, mult in zip(keys, _MIX):
            acc = acc + np.asarray(k, np.int64) * mult
        h = acc.astype(np.uint64)
        h = (h ^ (h >> np.uint64(30))) * _H2
        h = (h ^ (h >> np.uint64(27))) * _H3
        h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(40)).astype(np.float32) * np.float32(1.0 / 16777216.0)


def _cell(x, size):
    return np.floor(x / size).astype(np.int64)


def _band(x, hw, fp):
    """Fraction of a window of width fp centred at x covered by the band |x| <= hw (exact box filter)."""
    ifp = 1.0 / np.maximum(fp, 1e-6)
    return np.clip(np.minimum((hw - np.abs(x)) * ifp + 0.5, 2.0 * hw * ifp), 0.0, 1.0)


def _periodic(x, period):
    """Signed distance from x to the nearest multiple of period."""
    return np.mod(x + period / 2, period) - period / 2


def _fade(fp, scale):
    """Detail weight: 1 while a pixel covers under half a feature, 0 from a whole one."""
    return np.clip(2.0 - 2.0 * fp / scale, 0.0, 1.0)


def _noise(fp, scale, amp, *keys_and_coords):
    """Zero-mean hash noise on cells of `scale` metres, faded out with the footprint."""
    *keys, = keys_and_coords
    return amp * (hash01(*keys) - 0.5) * _fade(fp, scale)


def _road_albedo(L: Layout, s, l, fp, seed):
    g = L.asphalt + _noise(fp, 0.05, 0.12, _cell(s, 0.05), _cell(l, 0.05), seed)
    g = g + _noise(fp, 0.8, 0.035, _cell(s, 0.8), _cell(l, 0.8), seed + 1)
    lane = _periodic(l + L.lane_w / 2, L.lane_w)  # 0 at lane centres
    g = g - 0.035 * (_band(np.abs(lane) - 0.85, 0.3, fp))
    paint = np.zeros_like(s)
    dash = _band(np.mod(s, 9.0) - 1.5, 1.5, fp)
    for lat in (L.lane_w / 2, -L.lane_w / 2):
        paint = np.maximum(paint, _band(l - lat, 0.075, fp) * dash)
    paint = np.maximum(paint, _band(np.abs(l) - L.edge_l, 0.08, fp))
    in_park = (np.abs(l) > L.edge_l) & (np.abs(l) < L.kerb_l)
    paint = np.maximum(paint, in_park * _band(_periodic(s, 6.0), 0.05, fp))
    g = g * (1 - paint) + (0.55 + g) * paint
    return np.stack([g, g, g * 1.03], -1)


def _sidewalk_albedo(s, l, fp, seed):
    tile = 0.45
    joints = np.maximum(_band(_periodic(s, tile), 0.008, fp), _band(_periodic(l, tile), 0.008, fp))
    g = 0.60 + _noise(fp, 0.9, 0.08, _cell(s, tile), _cell(l, tile), seed + 3)
    g = g + _noise(fp, 0.04, 0.06, _cell(s, 0.04), _cell(l, 0.04), seed + 4)
    g = g * (1 - joints) + 0.38 * joints
    return np.stack([g, g * 0.98, g * 0.94], -1)


def _kerb_albedo(s, z, fp, seed):
    g = 0.72 + _noise(fp, 0.04, 0.08, _cell(s, 0.04), _cell(z, 0.04), seed + 5)
    g = g - 0.2 * _band(_periodic(s, 1.0), 0.006, fp)
    return np.stack([g, g, g * 0.98], -1)


def _facade_albedo(L: Layout, bi, face, s, l, z, fp, seed, brick_wall: bool):
    oid = L.box_id[bi]
    b = L.tex['boxes'][bi]
    par = L.tex['box_par'][bi]
    base = L.tex['box_rgb'][bi]
    frame = L.tex['box_rgb2'][bi]
    style, floor_h, spacing, win_w, win_h, sill, shop = par[:, :7].T
    along = np.isin(face, (rc.L0, rc.L1))
    h = np.where(along, s - b[:, 0], l - b[:, 2])
    width = np.where(along, b[:, 1] - b[:, 0], b[:, 3] - b[:, 2])
    zr = z - b[:, 4]
    # wall: bricks or plaster
    if brick_wall:
        row = _cell(zr, 0.075)
        hb = h + (row % 2) * 0.125
        brick_var = _noise(fp, 0.25, 0.22, oid, row, _cell(hb, 0.25), seed + 6)
        mortar = np.maximum(_band(_periodic(zr, 0.075), 0.007, fp), _band(_periodic(hb, 0.25), 0.007, fp))
        wall_f = (1 + brick_var) * (1 - mortar) + 1.35 * mortar
    else:
        wall_f = (1 + _noise(fp, 0.05, 0.10, oid, _cell(h, 0.05), _cell(zr, 0.05), seed + 7)
                  + _noise(fp, 0.7, 0.10, oid, _cell(h, 0.7), _cell(zr, 0.7), seed + 8))
    floor = np.floor(zr / floor_h)
    zf = zr - floor * floor_h
    band = _band(zf - 0.06, 0.1, fp) * (floor >= 1)
    wall_f = wall_f * (1 - band) + 1.2 * band
    wall = base * wall_f[:, None]
    # windows on a grid centred on the face, whole floors only
    ncols = np.floor((width - 0.6) / spacing)
    hh = h - 0.5 * (width - ncols * spacing)
    col = np.floor(hh / spacing)
    hc = hh - (col + 0.5) * spacing
    top = b[:, 5]
    ok = (col >= 0) & (col < ncols) & (b[:, 4] + (floor + 1) * floor_h <= top - 0.2)
    is_shop = (floor == 0) & (shop > 0.5)
    ww = np.where(is_shop, spacing - 0.35, win_w)
    wz0 = np.where(is_shop, 0.35, sill)
    wz1 = np.where(is_shop, floor_h - 0.55, sill + win_h)
    ok = ok & ((floor >= 1) | is_shop)
    wc = 0.5 * (wz0 + wz1)
    wh2 = 0.5 * (wz1 - wz0)
    win = ok * _band(hc, ww / 2, fp) * _band(zf - wc, wh2, fp)
    glass = ok * _band(hc, ww / 2 - 0.07, fp) * _band(zf - wc, wh2 - 0.07, fp)
    glass = glass * (1 - _band(hc, 0.03, fp))
    wid = hash01(oid, floor.astype(np.int64), col.astype(np.int64), seed + 9)
    refl = 0.10 + 0.45 * wid + 0.25 * np.clip((zf - wz0) / np.maximum(wz1 - wz0, 1e-3), 0, 1)
    glass_rgb = np.stack([0.20 * refl, 0.26 * refl, 0.34 * refl], -1)
    lit = (wid > 0.9)[:, None]
    glass_rgb = np.where(lit, np.array([0.78, 0.66, 0.42]), glass_rgb)
    out = wall * (1 - win)[:, None] + frame * (win - glass)[:, None] + glass_rgb * glass[:, None]
    roof = np.isin(face, (rc.Z0, rc.Z1))
    out[roof] = 0.28 + _noise(fp[roof], 0.1, 0.06, _cell(s[roof], 0.1), _cell(l[roof], 0.1), seed)[:, None]
    return out


def _car_albedo(L: Layout, bi, face, s, l, z, fp):
    b = L.tex['boxes'][bi]
    base = L.tex['box_rgb'][bi]
    facing = L.box_par[bi, 0]
    out = base.copy()
    zr = z - b[:, 4]
    ends = np.isin(face, (rc.S0, rc.S1))
    side = np.isin(face, (rc.L0, rc.L1))
    bumper = _band(zr - 0.08, 0.09, fp) * (side | ends)
    out = out * (1 - bumper)[:, None] + 0.08 * bumper[:, None]
    # door seams along the sides
    length = b[:, 1] - b[:, 0]
    u = (s - b[:, 0]) / length
    seam = side * np.maximum(_band((u - 0.36) * length, 0.01, fp), _band((u - 0.62) * length, 0.01, fp))
    out = out * (1 - 0.7 * seam)[:, None]
    # lamps and number plate on the ends
    w = b[:, 3] - b[:, 2]
    lat = l - 0.5 * (b[:, 2] + b[:, 3])
    top = b[:, 5] - b[:, 4]
    lampz = _band(zr - (top - 0.18), 0.07, fp)
    lamps = ends * lampz * _band(np.abs(lat) - (w / 2 - 0.3), 0.16, fp)
    rear = np.where(facing > 0, face == rc.S0, face == rc.S1)
    lamp_rgb = np.where(rear[:, None], np.array([0.75, 0.05, 0.04]), np.array([0.95, 0.93, 0.8]))
    out = out * (1 - lamps)[:, None] + lamp_rgb * lamps[:, None]
    plate = ends * _band(zr - 0.3, 0.06, fp) * _band(lat, 0.26, fp)
    out = out * (1 - plate)[:, None] + 0.9 * plate[:, None]
    return out


def _cabin_albedo(L: Layout, bi, face, s, l, z, fp):
    b = L.tex['boxes'][bi]
    base = L.tex['box_rgb'][bi]
    along = np.isin(face, (rc.L0, rc.L1))
    vertical = ~np.isin(face, (rc.Z0, rc.Z1))
    h = np.where(along, s - b[:, 0], l - b[:, 2])
    width = np.where(along, b[:, 1] - b[:, 0], b[:, 3] - b[:, 2])
    zr = z - b[:, 4]
    hgt = b[:, 5] - b[:, 4]
    glass = (vertical * _band(h - width / 2, width / 2 - 0.09, fp)
             * _band(zr - hgt / 2 + 0.02, hgt / 2 - 0.08, fp))
    pillar = along * _band(h - width / 2, 0.05, fp)
    glass = glass * (1 - pillar)
    refl = 0.08 + 0.12 * np.clip(zr / np.maximum(hgt, 1e-3), 0, 1)
    glass_rgb = np.stack([refl, refl * 1.1, refl * 1.3], -1)
    return base * (1 - glass)[:, None] + glass_rgb * glass[:, None]


def _wheel_albedo(L: Layout, bi, face, s, z, fp):
    b = L.tex['boxes'][bi]
    c = 0.5 * (b[:, 0] + b[:, 1])
    r = np.hypot(s - c, z - 0.33)
    side = np.isin(face, (rc.L0, rc.L1))
    hub = side * _band(r, 0.16, fp)
    g = 0.05 * (1 - hub) + 0.55 * hub
    return np.stack([g, g, g], -1)


@dataclass
class World:
    """Everything a ray can hit at one instant: the layout with its actors placed, the
    primitives and their hulls (``Primitives.bound_points``)."""

    layout: Layout
    prims: rc.Primitives
    bounds: tuple


class SyntheticStreet:
    """A procedural street driven by a camera rig, rendered by an exact analytic ray caster.

    The same scene renders any pose (e.g. the recorded trajectory shifted laterally) at any
    frame's instant, so it is the ground truth of shifted views, moving traffic included.
    Everything is deterministic from ``seed``; ``traffic=False`` leaves only parked cars.
    """

    def __init__(self, name: str = "demo", seed: int = 7, frames: int = 160, width: int = 832,
                 height: int = 480, curvature: float = 0.0, speed_mps: float = 8.0,
                 fps: float = 10.0, cameras=("front",), lidar: bool = False,
                 traffic: bool = True):
        cameras = camera_names(cameras)
        check_values({"seed": seed, "frames": frames, "width": width, "height": height,
                      "curvature": curvature, "speed_mps": speed_mps, "fps": fps})
        self.name = str(name)
        self.seed = int(seed)
        self.frames = int(frames)
        self.width = int(width)
        self.height = int(height)
        self.curvature = float(curvature)
        self.speed_mps = float(speed_mps)
        self.fps = float(fps)
        self.lidar = bool(lidar)
        self.arc = rc.RoadArc(self.curvature)
        s_min, s_max = drive(self.frames, self.speed_mps, self.fps, self.arc.kappa)
        self.traffic = bool(traffic)
        self.layout = build_layout(self.seed, self.arc, s_min, s_max,
                                   ego_speed=self.speed_mps if self.traffic else 0.0)
        L = self.layout
        self.prims = rc.Primitives(self.arc, L.kerb_l, KERB_H, L.boxes, L.cylinders, L.spheres)
        self._bounds = self.prims.bound_points()
        self._worlds: dict[int, World] = {}
        self.cameras = {c: camera_spec(c, self.width, self.height) for c in cameras}

    # -- actors -------------------------------------------------------------------------------

    def world_at(self, frame: int) -> World:
        """The street at frame ``frame``'s instant (frame / fps seconds), actors moved there."""
        movers = [m for m in self.layout.movers if m.moving]
        if not movers or frame == 0:
            return World(self.layout, self.prims, self._bounds)
        if frame not in self._worlds:
            if len(self._worlds) >= 16:
                self._worlds.pop(next(iter(self._worlds)))
            L = self.layout
            boxes = traffic.shifted_boxes(L.boxes, movers, frame / self.fps)
            prims = rc.Primitives(self.arc, L.kerb_l, KERB_H, boxes, L.cylinders, L.spheres)
            kinds, idx, pts = self._bounds
            rows = np.concatenate([m.rows for m in movers])
            pts = pts.copy()
            pts[rows] = rc.box_hull_points(self.arc, boxes[rows])  # boxes come first
            self._worlds[frame] = World(replace(L, boxes=boxes), prims, (kinds, idx, pts))
        return self._worlds[frame]

    def actors(self) -> list[Actor]:
        """Every actor's labelled track over the street's frames (traffic.track), in the world."""
        times = np.arange(self.frames) / self.fps
        ego_xy = self.ego2world()[:, :2, 3]
        found = (traffic.track(m, self.arc, times, ego_xy) for m in self.layout.movers)
        return [a for a in found if a is not None]

    # -- trajectory ---------------------------------------------------------------------------

    def arc_lengths(self) -> np.ndarray:
        """(frames,) arc length of the ego along the centreline."""
        return self.speed_mps * np.arange(self.frames) / self.fps

    def ego2world(self) -> np.ndarray:
        """(frames, 4, 4) float64 ego-to-world; world = first ego pose, ego origin on the road."""
        s = self.arc_lengths()
        x, y = self.arc.to_world(s, np.zeros_like(s))
        th = self.arc.heading(s)
        out = np.tile(np.eye(4), (self.frames, 1, 1))
        out[:, 0, 0] = np.cos(th)
        out[:, 0, 1] = -np.sin(th)
        out[:, 1, 0] = np.sin(th)
        out[:, 1, 1] = np.cos(th)
        out[:, 0, 3] = x
        out[:, 1, 3] = y
        return out

    def timestamps_us(self) -> np.ndarray:
        return np.round(np.arange(self.frames) * 1e6 / self.fps).astype(np.int64)

    def c2w(self, camera: str) -> np.ndarray:
        """(frames, 4, 4) camera-to-world (OpenCV axes) of a rig camera."""
        return self.ego2world() @ self.cameras[camera].cam2ego

    # -- rendering ----------------------------------------------------------------------------

    def render(self, c2w, K, width: int, height: int, threads: int | None = None,
               cull: bool = True, frames=None) -> dict:
        """Render views. c2w: (N, 4, 4) or (4, 4) camera-to-world, OpenCV; K: (3, 3);
        frames: the frame index (instant) of each view, (N,) or one int; None = frame 0.

        Pixel (v, u) samples the ray through image point (u + 0.5, v + 0.5). Frames are spread
        over ``threads`` threads (default: up to 2). cull=False tests every ray against every
        object: the same pixels, slowly (a reference for tests and benchmarks).
        Returns {'rgb': uint8 (N, H, W, 3), 'depth': float32 (N, H, W) z-depth (inf for sky),
        'sky': bool (N, H, W)}.
        """
        c2w = np.asarray(c2w, np.float64)
        if c2w.shape == (4, 4):
            c2w = c2w[None]
        if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
            raise ValueError(f"render: c2w must be (N, 4, 4) or (4, 4), got {c2w.shape}")
        K = np.asarray(K, np.float64)
        n = len(c2w)
        when = np.broadcast_to(np.asarray(0 if frames is None else frames, dtype=np.int64), (n,))
        out = {"rgb": np.zeros((n, height, width, 3), np.uint8),
               "depth": np.zeros((n, height, width), np.float32),
               "sky": np.zeros((n, height, width), bool)}

        def one(i):
            rgb, depth = self._render_one(c2w[i], K, int(width), int(height), cull,
                                          self.world_at(int(when[i])))
            out["rgb"][i] = rgb
            out["depth"][i] = depth
            out["sky"][i] = ~np.isfinite(depth)

        threads = threads or min(2, os.cpu_count() or 1, n)
        if threads > 1:
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(one, range(n)))
        else:
            for i in range(n):
                one(i)
        return out

    def render_frame(self, camera: str, index: int, c2w=None) -> dict:
        """One frame of a rig camera (optionally from another pose): dict as render() without N."""
        spec = self.cameras[camera]
        pose = self.c2w(camera)[index] if c2w is None else c2w
        views = self.render(pose, spec.K(), spec.width, spec.height, threads=1, frames=index)
        return {k: v[0] for k, v in views.items()}

    def _render_one(self, c2w, K, width, height, cull, world: World):
        hits, o, (dx, dy, dz) = rc.cast_camera(world.prims, c2w, K, width, height, world.bounds,
                                               cull)
        pixel_angle = 1.0 / (0.5 * (K[0, 0] + K[1, 1]))
        rgb = self.shade(hits, o, dx, dy, dz, pixel_angle, world)
        return rgb, hits.t.astype(np.float32)

    def _group_keys(self, kind, index):
        """Shading group per ray: sky, ground part, box material (facades split by wall style),
        cylinder, sphere. Sorting by it makes every group a contiguous run."""
        L = self.layout
        box_key = (_G_BOX + 2 * L.box_mat + (L.box_mat == FACADE) * (L.box_par[:, 0] > 0.5)).astype(np.int16)
        key = np.zeros(kind.shape, np.int16)
        key = np.where(kind == rc.GROUND, _G_GROUND + index, key)
        if len(box_key):
            key = np.where(kind == rc.BOX, box_key[np.minimum(index, len(box_key) - 1)], key)
        key = np.where(kind == rc.CYLINDER, _G_CYL, key)
        key = np.where(kind == rc.SPHERE, _G_SPH, key)
        return key.astype(np.int16)

    def shade(self, hits: rc.Hits, o, dx, dy, dz, pixel_angle: float,
              world: World | None = None) -> np.ndarray:
        """Colour (uint8, shape + (3,)) of cast rays; footprint-filtered textures, Lambert + sky.

        pixel_angle: angular size of a pixel (rad), for the texture filter footprint; world: the
        instant the rays were cast in (default frame 0).
        """
        world = world or self.world_at(0)
        L = world.layout
        f32 = np.float32
        shape = hits.t.shape
        kind = hits.kind.ravel()
        key = self._group_keys(kind, hits.index.ravel())
        order = np.argsort(key, kind="stable")
        key = key[order]
        t = hits.t.ravel()[order]
        index = hits.index.ravel()[order]
        face = hits.face.ravel()[order]
        dx, dy, dz = dx.ravel()[order], dy.ravel()[order], dz.ravel()[order]
        col = np.empty((t.size, 3), f32)  # in 0..255 (+0.5, so the cast to uint8 rounds)
        starts = np.concatenate([[0], np.flatnonzero(key[1:] != key[:-1]) + 1])
        group_keys = key[starts]
        ends = np.append(starts[1:], t.size)
        n_sky = int(ends[0]) if group_keys[0] == _G_SKY else 0
        if n_sky:
            col[:n_sky] = rc.sky_colour(dx[:n_sky], dy[:n_sky], dz[:n_sky], L.sun, L.zenith,
                                        L.horizon) * 255.0 + 0.5
        if n_sky < t.size:
            hit = slice(n_sky, t.size)
            th, hx, hy, hz = t[hit], dx[hit], dy[hit], dz[hit]
            px, py, pz = o[0] + th * hx, o[1] + th * hy, o[2] + th * hz
            s, l = self.arc.to_road(px, py)
            normal = np.empty((len(th), 3), f32)
            albedo = np.empty((len(th), 3), f32)
            s32, l32, px32, py32, pz32, th32, hx, hy, hz = (
                a.astype(f32) for a in (s, l, px, py, pz, th, hx, hy, hz))
            groups = [(int(g), slice(a - n_sky, b - n_sky)) for g, a, b in zip(group_keys, starts, ends)
                      if g != _G_SKY]
            for g, sl in groups:
                kind_g = _group_kind(g)
                part = g - _G_GROUND if kind_g == rc.GROUND else -1
                normal[sl] = rc.group_normals(world.prims, kind_g, part, index[hit][sl], face[hit][sl],
                                              px[sl], py[sl], pz[sl], s[sl])
            ndd = normal[:, 0] * hx + normal[:, 1] * hy + normal[:, 2] * hz
            # pixel footprint on the surface: range * pixel angle / cos(incidence)
            dn = np.sqrt(hx * hx + hy * hy + hz * hz)
            rng = th32 * dn
            fp = np.minimum(rng * dn * f32(pixel_angle) / np.maximum(np.abs(ndd), f32(0.1) * dn), f32(50.0))
            for g, sl in groups:
                albedo[sl] = self._albedo(L, g, index[hit][sl], face[hit][sl], s32[sl], l32[sl],
                                          px32[sl], py32[sl], pz32[sl], fp[sl])
            # Lambert with the normal turned towards the viewer, then aerial perspective: distant
            # surfaces fade towards the horizon colour
            light = rc.light(normal, -np.sign(ndd), L.sun.astype(f32))
            haze = rng / (rng + f32(900.0))
            col[hit] = albedo * (light * (1 - haze) * 255)[:, None] + (
                L.horizon.astype(f32) * 255)[None] * haze[:, None] + 0.5
        np.clip(col, 0.0, 255.0, out=col)
        # back to image order, moving each pixel as one 4-byte word
        rgba = np.empty((t.size, 4), np.uint8)
        rgba[:, :3] = col
        out = np.empty(t.size, np.uint32)
        out[order] = rgba.view(np.uint32).ravel()
        return out.view(np.uint8).reshape(shape + (4,))[..., :3]

    def _albedo(self, L: Layout, group: int, index, face, s, l, px, py, pz, fp):
        """Albedo (m, 3) float32 of one shading group's hits (L: the layout at that instant)."""
        seed = self.seed * 1000
        if group == _G_GROUND + rc.ROAD:
            return _road_albedo(L, s, l, fp, seed)
        if group == _G_GROUND + rc.SIDEWALK:
            return _sidewalk_albedo(s, l, fp, seed)
        if group == _G_GROUND + rc.KERB:
            return _kerb_albedo(s, pz, fp, seed)
        if group == _G_CYL:
            cyl = L.cylinders[index]
            ang = np.arctan2(py - cyl[:, 1], px - cyl[:, 0]).astype(np.float32)
            arc_len = ang * cyl[:, 2].astype(np.float32)
            bark = np.where(L.cyl_mat[index] == TRUNK, np.float32(0.35), np.float32(0.08))
            grain = hash01(L.cyl_id[index], _cell(arc_len, 0.03), _cell(pz, 0.12), seed) - 0.5
            v = 1 + bark * grain * _fade(fp, 0.06)
            return L.tex["cyl_rgb"][index] * v[:, None]
        if group == _G_SPH:
            leaf = hash01(L.sph_id[index], _cell(px, 0.12), _cell(py, 0.12), _cell(pz, 0.12), seed)
            v = 1 + 0.8 * (leaf - 0.5) * _fade(fp, 0.24)
            return L.tex["sph_rgb"][index] * v[:, None]
        material, brick = divmod(group - _G_BOX, 2)
        if material == FACADE:
            return _facade_albedo(L, index, face, s, l, pz, fp, seed, bool(brick))
        if material == CAR:
            return _car_albedo(L, index, face, s, l, pz, fp)
        if material == CABIN:
            return _cabin_albedo(L, index, face, s, l, pz, fp)
        if material == WHEEL:
            return _wheel_albedo(L, index, face, s, pz, fp)
        return L.tex["box_rgb"][index]

    # -- lidar --------------------------------------------------------------------------------

    def lidar_points(self, index: int) -> np.ndarray:
        """(M, 3) float32 world-frame returns of a roof LiDAR at frame ``index``.

        32 beams from -25 to +5 deg elevation x 512 azimuths, at 1.95 m above the ego origin,
        ranges up to 75 m; rays that hit nothing within range give no point.
        """
        ego = self.ego2world()[index]
        el = np.deg2rad(np.linspace(*LIDAR_ELEVATION_DEG, LIDAR_BEAMS))
        az = np.arange(LIDAR_AZIMUTHS) * (2 * np.pi / LIDAR_AZIMUTHS)
        el, az = np.meshgrid(el, az, indexing="ij")
        d_ego = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
        dirs = d_ego @ ego[:3, :3].T  # (beams, azimuths, 3), unit: t is range
        o = ego[:3, :3] @ np.array([0.0, 0.0, LIDAR_HEIGHT]) + ego[:3, 3]
        world = self.world_at(index)
        cands = self._lidar_candidates(o, ego, world.bounds)
        hits = rc.cast(world.prims, o, dirs[..., 0].copy(), dirs[..., 1].copy(), dirs[..., 2].copy(), cands)
        ok = hits.t <= LIDAR_MAX_RANGE
        return (o + hits.t[ok][:, None] * dirs[ok]).astype(np.float32)

    def _lidar_candidates(self, o, ego, bounds):
        """Per object within range, the azimuth columns its hull spans (as slices of the scan)."""
        kinds, idx, pts = bounds
        lo, hi = pts.min(1), pts.max(1)
        gap = np.maximum(np.maximum(lo - o, o - hi), 0.0)
        dist = np.linalg.norm(gap, axis=1)
        step = 2 * np.pi / LIDAR_AZIMUTHS
        cands = []
        heading = np.arctan2(ego[1, 0], ego[0, 0])
        for j in np.flatnonzero(dist <= LIDAR_MAX_RANGE)[np.argsort(dist[dist <= LIDAR_MAX_RANGE])]:
            p = pts[j] - o
            around = lo[j, 0] <= o[0] <= hi[j, 0] and lo[j, 1] <= o[1] <= hi[j, 1]
            if around:
                cands.append((int(kinds[j]), int(idx[j]), (slice(None), slice(None)), None))
                continue
            # a convex hull seen from outside spans the azimuths of its vertices
            ang = np.arctan2(p[:, 1], p[:, 0]) - heading
            centre = np.arctan2(np.sin(ang).mean(), np.cos(ang).mean())
            rel = np.angle(np.exp(1j * (ang - centre)))
            a0 = int(np.floor((centre + rel.min()) / step)) - 1
            a1 = int(np.floor((centre + rel.max()) / step)) + 2
            for lo_i, hi_i in ((a0, a1),) if a1 - a0 < LIDAR_AZIMUTHS else ((0, LIDAR_AZIMUTHS),):
                lo_m, hi_m = lo_i % LIDAR_AZIMUTHS, hi_i % LIDAR_AZIMUTHS
                pieces = [(lo_m, hi_m)] if lo_m < hi_m else [(lo_m, LIDAR_AZIMUTHS), (0, hi_m)]
                if hi_i - lo_i >= LIDAR_AZIMUTHS:
                    pieces = [(0, LIDAR_AZIMUTHS)]
                for p0, p1 in pieces:
                    if p1 > p0:
                        cands.append((int(kinds[j]), int(idx[j]), (slice(None), slice(p0, p1)), None))
        return cands
