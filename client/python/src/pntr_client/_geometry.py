"""Rigid-transform helpers: quaternions (w, x, y, z) <-> 3x3 rotation matrices, 4x4 poses, and the
conversion between a map's own frame conventions and ROS's (REP 103 z-up world, optical camera)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

Quaternion = tuple[float, float, float, float]


def quaternion_to_matrix(w: float, x: float, y: float, z: float) -> npt.NDArray[np.float64]:
    """The 3x3 rotation matrix of the quaternion (w, x, y, z), normalised first.

    Raises ValueError for a zero or non-finite quaternion.
    """
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not (math.isfinite(n) and n > 0.0):
        raise ValueError(f"quaternion ({w}, {x}, {y}, {z}) is not a rotation (zero or not finite)")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ],
        dtype=np.float64,
    )


def matrix_to_quaternion(r: npt.ArrayLike) -> Quaternion:
    """The unit quaternion (w, x, y, z), w >= 0, of a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    r00, r01, r02 = m[0]
    r10, r11, r12 = m[1]
    r20, r21, r22 = m[2]
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    n = math.sqrt(sum(c * c for c in q))
    sign = -1.0 if q[0] < 0.0 else 1.0
    w, x, y, z = (float(sign * c / n) for c in q)
    return (w, x, y, z)


def pose_matrix(translation: Sequence[float], rotation_wxyz: Sequence[float]) -> npt.NDArray[np.float64]:
    """The 4x4 homogeneous transform [R t; 0 0 0 1] from a translation (3,) and a quaternion (w, x, y, z)."""
    t = np.eye(4, dtype=np.float64)
    w, x, y, z = rotation_wxyz
    t[:3, :3] = quaternion_to_matrix(w, x, y, z)
    t[:3, 3] = translation
    return t


def check_pose(pose: npt.ArrayLike, what: str) -> npt.NDArray[np.float64]:
    """A 4x4 float64 rigid transform from `pose`: a 4x4 matrix, or a (3,) position (identity rotation).

    Raises ValueError naming `what` when the shape is wrong, a value is not finite, the last row is not
    (0, 0, 0, 1) or the upper-left 3x3 is not a rotation (orthonormal within 1e-3, determinant +1).
    """
    try:
        a = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} must be a 4x4 world_from_camera matrix or a (3,) position: {e}") from None
    if a.shape == (3,):
        out = np.eye(4, dtype=np.float64)
        out[:3, 3] = a
        a = out
    elif a.shape != (4, 4):
        raise ValueError(
            f"{what} has shape {a.shape}: expected a 4x4 world_from_camera matrix or a (3,) position (metres)"
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} holds a value that is not finite")
    if not np.allclose(a[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise ValueError(f"{what}: the last row of a 4x4 pose must be (0, 0, 0, 1), got {a[3].tolist()}")
    r = a[:3, :3]
    if not (np.allclose(r.T @ r, np.eye(3), atol=1e-3) and np.linalg.det(r) > 0.0):
        raise ValueError(f"{what}: the upper-left 3x3 is not a rotation matrix (orthonormal, determinant +1)")
    return a


# Habitat / OpenGL camera axes (x right, y up, looking along -z) <-> optical (x right, y down, z forward).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def _camera_flip(camera_axes: str) -> npt.NDArray[np.float64]:
    a = camera_axes.lower()
    if a == "habitat":
        return _FLIP_YZ
    if a in ("opencv", "optical"):
        return np.eye(3)
    raise ValueError(f"camera_axes must be 'habitat' or 'opencv', got {camera_axes!r}")


def ros_from_map_world(up_axis: str = "y") -> npt.NDArray[np.float64]:
    """The 3x3 rotation taking points of a map's world frame into the ROS (REP 103, z-up) frame: the
    identity for a z-up map, +90 degrees about x for a y-up map ((x, y, z) -> (x, -z, y)). The server
    reports it as `MapInfo.ros_from_map`.
    """
    if up_axis.lower() == "z":
        return np.eye(3)
    if up_axis.lower() != "y":
        raise ValueError(f"up_axis must be 'y' or 'z', got {up_axis!r}")
    return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def map_to_ros(pose: npt.ArrayLike, up_axis: str = "y", camera_axes: str = "habitat") -> npt.NDArray[np.float64]:
    """A 4x4 world_from_camera in a map's own conventions (`MapInfo.up_axis`, `MapInfo.camera_axes`)
    as ROS expects it: map_from_camera_optical with z up (what the server answers under
    frame_convention="ros"). The inverse is `ros_to_map`.
    """
    p = check_pose(pose, "pose")
    out = np.eye(4)
    r = ros_from_map_world(up_axis)
    out[:3, :3] = r @ p[:3, :3] @ _camera_flip(camera_axes)
    out[:3, 3] = r @ p[:3, 3]
    return out


def ros_to_map(pose: npt.ArrayLike, up_axis: str = "y", camera_axes: str = "habitat") -> npt.NDArray[np.float64]:
    """The inverse of `map_to_ros`: a ROS-convention 4x4 pose back in the map's frame and camera axes."""
    p = check_pose(pose, "pose")
    out = np.eye(4)
    r = ros_from_map_world(up_axis).T
    out[:3, :3] = r @ p[:3, :3] @ _camera_flip(camera_axes)
    out[:3, 3] = r @ p[:3, 3]
    return out


def rotate_covariance(covariance: npt.ArrayLike, rotation: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """A 6x6 pose covariance (ROS order: x, y, z, rotation about x, y, z, in the world frame)
    re-expressed after the world frame is rotated by the 3x3 `rotation`: J C J^T, J = diag(R, R).
    """
    c = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    r = np.asarray(rotation, dtype=np.float64)
    j = np.zeros((6, 6))
    j[:3, :3] = r
    j[3:, 3:] = r
    return j @ c @ j.T
