"""The street's actors: parked cars (static), moving cars in the lanes and crossing pedestrians.

An actor is a group of road boxes (``Layout.boxes`` rows) that moves rigidly in road coordinates
(s along the road, l to the left) with a constant velocity; a crossing pedestrian stops on the far
sidewalk (``l_stop``). Its box at time t is the union of its parts, shifted by ``offset(t)``, so
the ray caster renders exactly the truth the exported labels describe.

Lanes (``|l| < 1.5 lane_w``): the ego drives the centre lane; oncoming cars use the left lane
(driving towards -s), faster cars overtake in the right lane. Pedestrians cross the ego's lane
a few seconds before the ego gets there, never under its wheels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from paradrive import geometry
from paradrive.actors import Actor
from paradrive.synthetic.limits import along

# labels as a roof LiDAR would give them: only while the box centre is this close to the ego (m)
LABEL_RANGE_M = 75.0
PERSON_COLOURS = np.array([(0.15, 0.18, 0.35), (0.55, 0.12, 0.10), (0.80, 0.75, 0.65),
                           (0.20, 0.35, 0.22), (0.10, 0.10, 0.10), (0.85, 0.55, 0.15)])


@dataclass
class Mover:
    """One actor of the street. bbox: (6,) s0, s1, l0, l1, z0, z1 of its parts at t = 0;
    velocity: (ds/dt, dl/dt) m/s; yaw: heading relative to the road's (0, pi, +-pi/2)."""

    id: str
    cls: str
    rows: np.ndarray
    bbox: np.ndarray
    velocity: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    l_stop: float = np.inf

    @property
    def moving(self) -> bool:
        return self.velocity != (0.0, 0.0)

    def offset(self, t: float) -> tuple[float, float]:
        """(ds, dl) of the actor at time t (s) from where it is at t = 0."""
        lc = 0.5 * (self.bbox[2] + self.bbox[3])
        dl = float(np.clip(lc + self.velocity[1] * t, -self.l_stop, self.l_stop)) - lc
        return self.velocity[0] * t, dl

    def offsets(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ds, dl) at each of ``times`` (s): :meth:`offset` for all of them at once, the same
        float64 operations element by element."""
        lc = 0.5 * (self.bbox[2] + self.bbox[3])
        dl = np.clip(lc + self.velocity[1] * times, -self.l_stop, self.l_stop) - lc
        return self.velocity[0] * times, dl

    def size(self) -> np.ndarray:
        """length (along the heading), width, height."""
        s0, s1, l0, l1, z0, z1 = self.bbox
        along, across = s1 - s0, l1 - l0
        if abs(np.sin(self.yaw)) > 0.5:
            along, across = across, along
        return np.array([along, across, z1 - z0])


def shifted_boxes(boxes: np.ndarray, movers: list[Mover], t: float) -> np.ndarray:
    """Copy of the layout's boxes (nb, 6) with every moving actor's parts where they are at t."""
    out = boxes.copy()
    for m in movers:
        if m.moving:
            ds, dl = m.offset(t)
            out[m.rows] += np.array([ds, ds, dl, dl, 0.0, 0.0])
    return out


def track(mover: Mover, arc, times: np.ndarray, ego_xy: np.ndarray) -> Actor | None:
    """The actor's labelled track at frame times (F,) s; ego_xy (F, 2) the ego positions.

    Frames where the box centre is farther than LABEL_RANGE_M from the ego carry no label.
    """
    s0, s1, l0, l1, z0, z1 = mover.bbox
    ds, dl = mover.offsets(np.asarray(times, np.float64))
    sc = 0.5 * (s0 + s1) + ds
    lc = 0.5 * (l0 + l1) + dl
    x, y = arc.to_world(sc, lc)
    near = np.hypot(x - ego_xy[:, 0], y - ego_xy[:, 1]) <= LABEL_RANGE_M
    if not near.any():
        return None
    heading = arc.heading(sc) + mover.yaw
    poses = [geometry.make_pose(geometry.rotation_about("z", float(h)), [xx, yy, 0.5 * (z0 + z1)])
             for h, xx, yy in zip(heading[near], x[near], y[near])]
    cls = "vehicle" if mover.cls == "car" else "pedestrian"
    return Actor(id=f"synthetic:{mover.id}", cls=cls, rigid=cls == "vehicle", size=mover.size(),
                 frames=np.flatnonzero(near).astype(np.int64), box2world=np.stack(poses))


def lane_cars(g, lane_l: float, direction: float, speed: float, s_min: float, s_max: float,
              add_car) -> list[tuple]:
    """Place cars along one lane (in order of s, so a longer street keeps a shorter one's).

    add_car(g, s, lc, facing) adds one car's boxes and returns (rows, bbox). Returns the
    Mover arguments (rows, bbox, velocity, yaw) of each car.
    """
    cars = []
    s = s_min + g.uniform(0.0, 15.0)
    for _ in along(s, s_max, 22.0):   # the next car's rear is 22 m at least past this one's front
        if s >= s_max:
            break
        rows, bbox = add_car(g, s, lane_l + g.uniform(-0.2, 0.2), direction)
        cars.append((rows, bbox, (direction * speed * g.uniform(0.97, 1.03), 0.0),
                     0.0 if direction > 0 else np.pi))
        s = bbox[1] + g.uniform(22.0, 55.0)
    return cars


def crossing_people(g, street_half: float, ego_speed: float, s_min: float, s_max: float,
                    add_person) -> list[tuple]:
    """Pedestrians crossing from kerb to kerb; each is in the ego's lane 3 to 6 s before the ego
    gets to it, then stops on the far sidewalk (at ``street_half`` from the centreline).

    add_person(g, s, lc) adds one person's boxes and returns (rows, bbox). Returns the Mover
    arguments (rows, bbox, velocity, yaw, l_stop) of each person.
    """
    people = []
    s = s_min + g.uniform(20.0, 40.0)
    for _ in along(s, s_max, 35.0):
        if s >= s_max:
            break
        side = 1.0 if g.random() < 0.5 else -1.0  # the side it starts from
        speed = g.uniform(1.2, 1.6)
        t_centre = max(s, 0.0) / ego_speed - g.uniform(3.0, 6.0)
        # where it is at t = 0, walking towards -side and at l = 0 at t_centre
        l_now = float(np.clip(side * speed * t_centre, -street_half, street_half))
        rows, bbox = add_person(g, s, l_now)
        people.append((rows, bbox, (0.0, -side * speed), -side * np.pi / 2, street_half))
        s += g.uniform(35.0, 80.0)
    return people
