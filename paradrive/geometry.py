"""SE(3) helpers, the lateral shift and the relative pose, exactly as docs/conventions.md fixes them.

Frames: ego (vehicle) x forward, y left, z up; camera OpenCV x right, y down, z forward.
Poses are 4x4 homogeneous matrices in float64; every function takes a single pose (4, 4) or a
batch (..., 4, 4) and broadcasts.
"""

from __future__ import annotations

import numpy as np

# Rotation taking a vector in OpenCV camera axes (x right, y down, z forward) to the
# "vehicle-style" camera axes used by Waymo calibrations (x forward, y left, z up).
OPENCV_TO_FLU = np.array(
    [[0.0, 0.0, 1.0],
     [-1.0, 0.0, 0.0],
     [0.0, -1.0, 0.0]]
)


def as_pose(matrix) -> np.ndarray:
    """Array of poses (..., 4, 4) in float64 from nested lists or a flat 16-vector."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape[-1:] == (16,):
        m = m.reshape(m.shape[:-1] + (4, 4))
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"expected (..., 4, 4) or (..., 16) pose, got shape {m.shape}")
    return m


def make_pose(rotation, translation) -> np.ndarray:
    """Pose (..., 4, 4) from rotation (..., 3, 3) and translation (..., 3)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    batch = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    pose = np.zeros(batch + (4, 4))
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = translation
    pose[..., 3, 3] = 1.0
    return pose


def invert(pose) -> np.ndarray:
    """Inverse of rigid poses (..., 4, 4) using R^T, exact for rotations."""
    pose = as_pose(pose)
    rot_t = np.swapaxes(pose[..., :3, :3], -1, -2)
    return make_pose(rot_t, -np.einsum("...ij,...j->...i", rot_t, pose[..., :3, 3]))


def translation(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    """Pure translation (4, 4)."""
    return make_pose(np.eye(3), [x, y, z])


def rotation_about(axis: str, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) by ``angle`` radians about ``axis`` in {'x','y','z'} (right-handed)."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)
    raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")


def quaternion_to_rotation(q) -> np.ndarray:
    """Rotation (..., 3, 3) from unit quaternions (..., 4) in (w, x, y, z) order (nuScenes order)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotation_to_quaternion(rotation) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 from a rotation matrix (3, 3)."""
    r = np.asarray(rotation, dtype=np.float64)
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    out = np.asarray(q)
    return out if out[0] >= 0 else -out


def is_rigid(pose, tol: float = 1e-5) -> np.ndarray:
    """True where pose (..., 4, 4) is finite, has an orthonormal rotation with det +1 and a [0 0 0 1] row."""
    pose = as_pose(pose)
    finite = np.isfinite(pose).all(axis=(-1, -2))
    rot = np.nan_to_num(pose[..., :3, :3])
    orth = np.abs(np.einsum("...ji,...jk->...ik", rot, rot) - np.eye(3)).max(axis=(-1, -2)) < tol
    det = np.abs(np.linalg.det(rot) - 1.0) < tol
    last = np.abs(np.nan_to_num(pose[..., 3, :]) - [0, 0, 0, 1]).max(axis=-1) < tol
    return finite & orth & det & last


def lateral_shift(c2w, ego2world, offset_m: float) -> np.ndarray:
    """Shift cameras to a parallel lane ``offset_m`` metres to the ego's left (negative = right).

    ``c2w_shifted = ego2world · Translate(0, d, 0) · world2ego · c2w``: the vehicle moves along its
    own y (left) axis, each camera keeps its orientation, and a tilted or side camera still moves
    horizontally (never along the camera's own x axis).

    c2w: (..., 4, 4) camera-to-world, OpenCV. ego2world: (..., 4, 4) the ego pose of the same frame.
    Returns (..., 4, 4).
    """
    c2w = as_pose(c2w)
    ego2world = as_pose(ego2world)
    return ego2world @ translation(y=offset_m) @ invert(ego2world) @ c2w


def relative_pose(c2w_target, c2w_source) -> np.ndarray:
    """ΔT = T_{t←s} = inv(c2w_target) · c2w_source, per frame.

    Maps points in the source camera frame to the target camera frame. For a pure lateral shift
    by d it is a translation of length |d|. Shapes (..., 4, 4) -> (..., 4, 4).
    """
    return invert(c2w_target) @ as_pose(c2w_source)


def target_in_source(c2w_target, c2w_source) -> np.ndarray:
    """T_{s←t} = inv(c2w_source) · c2w_target, per frame: the target camera's pose in the source
    camera's coordinates at the same frame, the inverse of :func:`relative_pose`.

    This is ReCamMaster's sign (its camera input is the target camera seen from the condition
    camera) without its reference to the condition's first frame, so it holds no ego motion: for a
    forward camera and ``offset_m = +d`` (the source on the target's left) it is ``(+d, 0, 0)``.
    Shapes (..., 4, 4) -> (..., 4, 4).
    """
    return invert(c2w_source) @ as_pose(c2w_target)


def recammaster_per_frame_camera(rel_pose, every: int = 1) -> np.ndarray:
    """The camera input in ReCamMaster's sign, per frame, from ``rel_pose`` = T_{t←s}.

    Row k is the top 3x4 of ``inv(rel_pose[every * k])`` = inv(c2w_source) · c2w_target at that
    frame (:func:`target_in_source`), flattened row-major. rel_pose (..., F, 4, 4) ->
    (..., ceil(F / every), 12) float32; ``every = 4`` takes one pose per Wan latent frame of a
    video's rel_pose, ``every = 1`` keeps every pose (a latent cache's, already one per latent frame).
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    rel = as_pose(rel_pose)[..., ::every, :, :]
    return invert(rel)[..., :3, :4].reshape(rel.shape[:-2] + (12,)).astype(np.float32)


def scale_intrinsics(fx: float, fy: float, cx: float, cy: float, sx: float, sy: float):
    """Intrinsics after resizing an image by (sx, sy): fx, cx scale by sx and fy, cy by sy."""
    return fx * sx, fy * sy, cx * sx, cy * sy


def project(points_world, c2w, K) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points (M, 3) into a camera; returns pixels (M, 2) and z-depth (M,)."""
    pts = np.asarray(points_world, dtype=np.float64)
    w2c = invert(c2w)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    uv = (cam[:, :2] / z[:, None]) * [K[0][0], K[1][1]] + [K[0][2], K[1][2]]
    return uv, z


def as_floats(m) -> list[float]:
    """An array as a flat list of Python floats, row-major (the JSON form of a pose, a
    quaternion, a translation)."""
    return [float(x) for x in np.asarray(m, dtype=np.float64).reshape(-1)]


def arc_length(c2w) -> np.ndarray:
    """Distance travelled (N,) along a camera path (N, 4, 4): 0 at the first pose, then the sum
    of the straight steps between consecutive camera centres."""
    centres = as_pose(c2w)[:, :3, 3]
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=-1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def slerp(rot_a, rot_b, t) -> np.ndarray:
    """Rotations (N, 3, 3) a fraction ``t`` (N,) of the way from ``rot_a`` to ``rot_b`` (N, 3, 3)
    along the shorter great arc of their unit quaternions."""
    qa = np.stack([rotation_to_quaternion(r) for r in np.asarray(rot_a, dtype=np.float64)])
    qb = np.stack([rotation_to_quaternion(r) for r in np.asarray(rot_b, dtype=np.float64)])
    dot = np.einsum("ni,ni->n", qa, qb)
    qb = np.where(dot[:, None] < 0, -qb, qb)  # q and -q are one rotation: take the short way
    angle = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    t = np.asarray(t, dtype=np.float64)
    small = angle < 1e-9
    sin = np.where(small, 1.0, np.sin(angle))
    wa = np.where(small, 1.0 - t, np.sin((1.0 - t) * angle) / sin)
    wb = np.where(small, t, np.sin(t * angle) / sin)
    return quaternion_to_rotation(wa[:, None] * qa + wb[:, None] * qb)


def longitudinal_shift(c2w, offset_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Move each camera ``offset_m`` metres along its own recorded path (negative = behind).

    The pose of frame i goes to where the path is ``arc_length[i] + offset_m`` along: the
    centre interpolated linearly and the rotation slerped between the two recorded frames
    around that point, so the camera looks where the recording looked there.

    c2w: (N, 4, 4) camera-to-world, OpenCV, the recorded path in frame order. Returns the
    shifted poses (N, 4, 4) and ``on_path`` (N,) bool: False where the point falls before the
    first or after the last frame (that pose is the recorded one, and must not be rendered).
    """
    c2w = as_pose(c2w)
    arc = arc_length(c2w)
    want = arc + float(offset_m)
    on_path = (want >= -1e-9) & (want <= arc[-1] + 1e-9)
    j = np.clip(np.searchsorted(arc, want, side="right") - 1, 0, max(len(arc) - 2, 0))
    k = np.minimum(j + 1, len(arc) - 1)
    span = arc[k] - arc[j]
    t = np.where(span > 0, (want - arc[j]) / np.where(span > 0, span, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    centres = c2w[j, :3, 3] + t[:, None] * (c2w[k, :3, 3] - c2w[j, :3, 3])
    shifted = make_pose(slerp(c2w[j, :3, :3], c2w[k, :3, :3], t), centres)
    return np.where(on_path[:, None, None], shifted, c2w), on_path
