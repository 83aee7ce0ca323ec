"""Rigid transforms with an explicit direction, and quaternion helpers.

One convention everywhere (see ``docs/CONVENTIONS.md``): a ``Pose`` named ``T_ab``
maps points expressed in frame *b* into frame *a*::

    X_a = T_ab.R @ X_b + T_ab.t

The pose we report for a camera is ``T_wc`` (camera-to-world): its ``t`` is the
camera centre in the world. Quaternions are Hamilton, unit, ordered
``(qx, qy, qz, qw)`` (scalar last), as in TUM files and on the wire.

Only numpy is used, so clients import this without torch or scipy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

__all__ = [
    "Pose",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "rotvec_to_rotmat",
    "rotmat_to_rotvec",
    "look_at",
    "rotation_angle_deg",
]


def quat_to_rotmat(q_xyzw: Sequence[float] | np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` -> 3x3 rotation matrix. Normalises the input."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f"quaternion must be 4 finite numbers (qx qy qz qw), got {q_xyzw!r}")
    n = np.linalg.norm(q)
    if n < 1e-12:
        raise ValueError("quaternion has zero length")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion ``(qx, qy, qz, qw)`` with ``qw >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rotvec_to_rotmat(rv: Sequence[float] | np.ndarray) -> np.ndarray:
    """Axis-angle vector (radians) -> rotation matrix (Rodrigues)."""
    rv = np.asarray(rv, dtype=np.float64)
    theta = np.linalg.norm(rv)
    if theta < 1e-12:
        K = _skew(rv)
        return np.eye(3) + K
    k = rv / theta
    K = _skew(k)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def rotmat_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> axis-angle vector (radians)."""
    q = rotmat_to_quat(R)
    s = np.linalg.norm(q[:3])
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(s, q[3])
    return q[:3] / s * angle


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (numerically safe near 0 and 180)."""
    return float(np.degrees(np.linalg.norm(rotmat_to_rotvec(R))))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


def _orthonormalise(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        U[:, -1] *= -1
        Rn = U @ Vt
    return Rn


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``T_ab``: ``X_a = R @ X_b + t``. Immutable; float64.

    Name variables after their direction (``T_wc`` camera-to-world,
    ``T_cw`` world-to-camera) and compose with ``@``: ``T_wc = T_wb @ T_bc``.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.t, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("pose has non-finite values")
        if abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise ValueError("pose rotation is not a rotation matrix")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # ---- construction -------------------------------------------------
    @classmethod
    def identity(cls) -> "Pose":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T: np.ndarray, *, orthonormalise: bool = False) -> "Pose":
        T = np.asarray(T, dtype=np.float64)
        if T.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"expected a 4x4 or 3x4 matrix, got shape {T.shape}")
        R = _orthonormalise(T[:3, :3]) if orthonormalise else T[:3, :3]
        return cls(R, T[:3, 3])

    @classmethod
    def from_quat_t(cls, q_xyzw: Sequence[float], t: Sequence[float]) -> "Pose":
        """From a Hamilton quaternion ``(qx, qy, qz, qw)`` and a translation."""
        return cls(quat_to_rotmat(q_xyzw), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_rotvec_t(cls, rotvec: Sequence[float], t: Sequence[float]) -> "Pose":
        return cls(rotvec_to_rotmat(rotvec), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_tum(cls, values: Sequence[float]) -> "Pose":
        """From the seven TUM numbers ``tx ty tz qx qy qz qw``."""
        if len(values) != 7:
            raise ValueError(f"a TUM pose has 7 numbers (tx ty tz qx qy qz qw), got {len(values)}")
        return cls.from_quat_t(values[3:7], values[0:3])

    # ---- views ---------------------------------------------------------
    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def quat_xyzw(self) -> np.ndarray:
        return rotmat_to_quat(self.R)

    def rotvec(self) -> np.ndarray:
        return rotmat_to_rotvec(self.R)

    def to_tum(self) -> np.ndarray:
        """The seven TUM numbers ``tx ty tz qx qy qz qw``."""
        return np.concatenate([self.t, self.quat_xyzw()])

    # ---- algebra --------------------------------------------------------
    def inverse(self) -> "Pose":
        Rt = self.R.T
        return Pose(Rt, -Rt @ self.t)

    def __matmul__(self, other: "Pose") -> "Pose":
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def transform(self, points: np.ndarray) -> np.ndarray:
        """Apply to points of shape (..., 3); keeps float32 input float32."""
        p = np.asarray(points)
        dtype = p.dtype if p.dtype in (np.float32, np.float64) else np.float64
        out = p @ self.R.T.astype(dtype) + self.t.astype(dtype)
        return out.astype(dtype, copy=False)

    def distance_to(self, other: "Pose") -> tuple[float, float]:
        """(translation distance in the target frame, rotation angle in degrees) between two poses."""
        d = self.inverse() @ other
        return float(np.linalg.norm(self.t - other.t)), rotation_angle_deg(d.R)

    def interpolate(self, other: "Pose", alpha: float) -> "Pose":
        """Geodesic interpolation: alpha=0 gives self, alpha=1 gives other."""
        d = self.inverse() @ other
        Rm = self.R @ rotvec_to_rotmat(rotmat_to_rotvec(d.R) * alpha)
        return Pose(Rm, (1 - alpha) * self.t + alpha * other.t)

    def __repr__(self) -> str:
        t = ", ".join(f"{v:.4f}" for v in self.t)
        q = ", ".join(f"{v:.4f}" for v in self.quat_xyzw())
        return f"Pose(t=[{t}], q_xyzw=[{q}])"


def look_at(eye: Iterable[float], target: Iterable[float], up: Iterable[float] = (0, 0, 1)) -> Pose:
    """Camera-to-world pose ``T_wc`` of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any x
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.stack([x, y, z], axis=1), eye)


def yaw_sweep(position: Iterable[float], hfov_deg: float, overlap: float = 0.7,
              pitches_deg: Iterable[float] = (0.0,), min_yaws: int = 4) -> list[Pose]:
    """Camera-to-world poses at ``position`` looking every way round (world z up): yaw steps of ``overlap`` x the
    horizontal field of view ``hfov_deg`` (at least ``min_yaws``), each at every pitch in ``pitches_deg``, no roll."""
    p = np.asarray(position, dtype=np.float64)
    n_yaw = max(min_yaws, int(np.ceil(360.0 / (overlap * hfov_deg))))
    poses = []
    for i in range(n_yaw):
        yaw = 2 * np.pi * i / n_yaw
        for pitch in pitches_deg:
            pr = np.radians(pitch)
            d = np.array([np.cos(yaw) * np.cos(pr), np.sin(yaw) * np.cos(pr), np.sin(pr)])
            poses.append(look_at(p, p + d, (0, 0, 1)))
    return poses
