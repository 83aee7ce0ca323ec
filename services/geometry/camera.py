"""The pinhole camera model of ``camera.json`` (OpenCV, pixel centres at integer coordinates).

``{"width": W, "height": H, "fx": .., "fy": .., "cx": .., "cy": .., "distortion": [k1, k2, p1, p2, k3]}``

Only numpy and OpenCV: clients import this without torch.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

__all__ = ["Camera", "CameraError"]


class CameraError(ValueError):
    """Intrinsics that cannot describe a real camera; the message says which field and why."""


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        dist = tuple(float(d) for d in (self.distortion or ()))
        if len(dist) < 5:
            dist = dist + (0.0,) * (5 - len(dist))
        elif len(dist) in (8, 12, 14) and not any(dist[5:]):
            # OpenCV's longer models (rational k4-k6, thin prism, tilt: ROS' rational_polynomial camera_info has 8) with
            # those terms zero are the 5-term model; non-zero ones are not (validate says so)
            dist = dist[:5]
        object.__setattr__(self, "distortion", dist)
        self.validate()

    # ---- validation ----------------------------------------------------
    def validate(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0 or v > 16384:
                raise CameraError(f"camera {name} must be a positive integer <= 16384, got {v!r}")
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
                raise CameraError(f"camera {name} must be a finite number, got {v!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if max(self.fx, self.fy) > 100 * max(self.width, self.height):
            raise CameraError(f"camera focal length {max(self.fx, self.fy)} is absurd for a {self.width}x{self.height} image")
        if not (-self.width <= self.cx <= 2 * self.width and -self.height <= self.cy <= 2 * self.height):
            raise CameraError(f"principal point ({self.cx}, {self.cy}) is far outside the {self.width}x{self.height} image")
        if len(self.distortion) != 5 or not all(math.isfinite(d) for d in self.distortion):
            raise CameraError(f"distortion must be 5 finite numbers [k1, k2, p1, p2, k3] (OpenCV's model; its longer "
                              f"ones only with their further terms zero), got {self.distortion!r}")

    # ---- I/O -----------------------------------------------------------
    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in d]
        if missing:
            raise CameraError(f"camera is missing fields: {', '.join(missing)}")
        try:
            return cls(
                width=int(d["width"]) if float(d["width"]).is_integer() else d["width"],
                height=int(d["height"]) if float(d["height"]).is_integer() else d["height"],
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                distortion=tuple(float(x) for x in d.get("distortion", [0, 0, 0, 0, 0])),
            )
        except (TypeError, ValueError) as e:
            if isinstance(e, CameraError):
                raise
            raise CameraError(f"camera fields are not numbers: {e}") from None

    def to_dict(self) -> dict:
        return {
            "width": int(self.width),
            "height": int(self.height),
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "distortion": [float(x) for x in self.distortion],
        }

    @classmethod
    def load(cls, path: str | Path) -> "Camera":
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise CameraError(f"{path}: no such camera file") from None
        except json.JSONDecodeError as e:
            raise CameraError(f"{path}: not valid JSON ({e})") from None
        try:
            return cls.from_dict(d)
        except CameraError as e:
            raise CameraError(f"{path}: {e}") from None

    def save(self, path: str | Path) -> None:
        from services.io.atomic import atomic_write_text

        atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    # ---- derived -------------------------------------------------------
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, distortion=(0, 0, 0, 0, 0)) -> "Camera":
        f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2, tuple(distortion))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=np.float64)

    @property
    def is_distorted(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    def undistorted(self) -> "Camera":
        """The same camera without lens distortion."""
        return replace(self, distortion=(0.0, 0.0, 0.0, 0.0, 0.0))

    def scaled(self, s: float) -> "Camera":
        """The camera for an image resized by ``s`` (pixel centres kept at integers)."""
        w, h = max(1, round(self.width * s)), max(1, round(self.height * s))
        sx, sy = w / self.width, h / self.height
        return replace(
            self,
            width=w,
            height=h,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    # ---- projection ----------------------------------------------------
    def project(self, X_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points in the camera frame (N,3) -> (pixels (N,2), depth z (N,)). Applies distortion."""
        X = np.asarray(X_cam, dtype=np.float64).reshape(-1, 3)
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = X[:, 0] / z
            y = X[:, 1] / z
        x, y = self._distort(x, y)
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1), z

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k1, k2, p1, p2, k3 = self.distortion
        if not self.is_distorted:
            return x, y
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) -> normalised image coordinates (N,2) (x/z, y/z).

        Newton iterations on the OpenCV model (exact to ~1e-12 within the image for
        realistic lenses); pure numpy so results do not depend on the OpenCV version.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        xd = (uv[:, 0] - self.cx) / self.fx
        yd = (uv[:, 1] - self.cy) / self.fy
        if not self.is_distorted or len(uv) == 0:
            return np.stack([xd, yd], axis=1)
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xd.copy(), yd.copy()
        for _ in range(20):
            r2 = x * x + y * y
            rad = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            drad = k1 + 2 * k2 * r2 + 3 * k3 * r2 * r2  # d rad / d r2
            fx = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
            fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
            j11 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
            j12 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
            j21 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
            j22 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (j22 * fx - j12 * fy) / det
            dy = (-j21 * fx + j11 * fy) / det
            x -= dx
            y -= dy
            if max(np.abs(dx).max(), np.abs(dy).max()) < 1e-13:
                break
        return np.stack([x, y], axis=1)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) float64 ray directions in the camera frame with z = 1, one per pixel centre (undistorted)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        xy = self.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
        rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return rays.reshape(self.height, self.width, 3)

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixels (N,2) with z-depth (N,) -> points in the camera frame (N,3)."""
        xy = self.undistort_points(uv)
        d = np.asarray(depth, dtype=np.float64).reshape(-1, 1)
        return np.concatenate([xy * d, d], axis=1)
