"""Textured triangle meshes for simulated sites, built from boxes, quads and walls with openings."""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.io.atomic import atomic_write
from services.sim.materials import MATERIALS, MaterialLibrary

__all__ = ["Mesh", "MeshBuilder", "turn_about_z"]


def turn_about_z(points: np.ndarray, centre_xy, yaw: float, shift_xy=(0.0, 0.0)) -> np.ndarray:
    """Points (N, 3) turned by ``yaw`` (radians) about the vertical through ``centre_xy``, then shifted along the
    floor by ``shift_xy``."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.array(points, dtype=np.float64)
    d = out[:, :2] - np.asarray(centre_xy, float)
    out[:, 0] = centre_xy[0] + c * d[:, 0] - s * d[:, 1] + shift_xy[0]
    out[:, 1] = centre_xy[1] + s * d[:, 0] + c * d[:, 1] + shift_xy[1]
    return out


@dataclass
class Mesh:
    vertices: np.ndarray  # (V, 3) float64, world frame (z up)
    faces: np.ndarray  # (F, 3) int32
    uv: np.ndarray  # (F, 3, 2) float64 texture coordinates per corner, in texture repeats
    material: np.ndarray  # (F,) int32 index into MATERIALS
    objects: np.ndarray | None = None  # (F,) int32: the movable object a face belongs to (furniture, stock), -1 for
    #                                    the building; None: nothing is movable (meshes saved before objects existed)
    parents: np.ndarray | None = None  # (objects,) int32: the object each one rests on (a monitor on its desk), -1: none

    def object_ids(self) -> np.ndarray:
        """(F,) int32 object per face, -1 where a face belongs to no movable object."""
        return self.objects if self.objects is not None else np.full(self.n_faces, -1, np.int32)

    def object_parents(self) -> np.ndarray:
        """(objects,) int32: the object each movable object rests on, -1 where none."""
        if self.parents is not None:
            return self.parents
        return np.full(max(int(self.object_ids().max()) + 1, 0), -1, np.int32)

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))

    def face_normals(self) -> np.ndarray:
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def uv_density(self) -> np.ndarray:
        """Texture repeats per metre on each face (sqrt of uv area / world area)."""
        tri = self.vertices[self.faces]
        wa = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        d1 = self.uv[:, 1] - self.uv[:, 0]
        d2 = self.uv[:, 2] - self.uv[:, 0]
        ua = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
        return np.sqrt(ua / np.maximum(wa, 1e-12))

    def save(self, path: str | Path) -> None:
        with atomic_write(path, "wb") as f:
            np.savez_compressed(f, vertices=self.vertices, faces=self.faces, uv=self.uv, material=self.material,
                                objects=self.object_ids(), parents=self.object_parents())

    @classmethod
    def load(cls, path: str | Path) -> "Mesh":
        with np.load(path) as z:
            return cls(z["vertices"], z["faces"], z["uv"], z["material"], z["objects"] if "objects" in z else None,
                       z["parents"] if "parents" in z else None)


class MeshBuilder:
    """Accumulates quads and boxes; ``rng`` jitters texture offsets so repeated materials do not look identical."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self._v: list[np.ndarray] = []
        self._f: list[np.ndarray] = []
        self._uv: list[np.ndarray] = []
        self._m: list[int] = []
        self._o: list[int] = []
        self._nv = 0
        self._object = -1  # the movable object faces are added to now (-1: the building)
        self._parents: list[int] = []  # per object, the one it rests on (-1: none)

    @contextmanager
    def movable(self):
        """Faces added inside belong to one movable object (a desk with its legs, a pallet with its boxes): what
        ``services.sim.changes`` may move or take away between the scan and the camera's day. Nested, an object rests
        on the one around it (a monitor on its desk): it goes where that one goes, and may be moved on its own."""
        outer, self._object = self._object, len(self._parents)
        self._parents.append(outer)
        try:
            yield
        finally:
            self._object = outer

    def quad(self, p0, p1, p2, p3, material: str) -> None:
        """A planar quad p0-p1-p2-p3 (p1 along the texture's u from p0, p3 along v)."""
        P = np.array([p0, p1, p2, p3], dtype=np.float64)
        mid = MaterialLibrary.id(material)
        size = MATERIALS[mid].size_m
        lu = np.linalg.norm(P[1] - P[0])
        lv = np.linalg.norm(P[3] - P[0])
        if lu < 1e-9 or lv < 1e-9:
            return
        if size > 0:
            off = self.rng.random(2)
            uvq = np.array([[0, 0], [lu, 0], [lu, lv], [0, lv]]) / size + off
        else:  # stretched once (posters): image upright when v points down the wall
            uvq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
        base = self._nv
        self._v.append(P)
        self._nv += 4
        for a, b, c in ((0, 1, 2), (0, 2, 3)):
            self._f.append(np.array([base + a, base + b, base + c]))
            self._uv.append(uvq[[a, b, c]])
            self._m.append(mid)
            self._o.append(self._object)

    def box(self, lo, hi, material: str | dict, skip: tuple[str, ...] = (), yaw: float = 0.0) -> None:
        """Axis-aligned box; ``material`` may map face names (-x +x -y +y -z +z) to materials; ``yaw`` (radians)
        turns it about the vertical through its centre."""
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        mats = material if isinstance(material, dict) else {}
        default = material if isinstance(material, str) else mats.get("default", "painted_wall")
        faces = {
            "-x": ((x0, y1, z1), (x0, y0, z1), (x0, y0, z0), (x0, y1, z0)),
            "+x": ((x1, y0, z1), (x1, y1, z1), (x1, y1, z0), (x1, y0, z0)),
            "-y": ((x0, y0, z1), (x1, y0, z1), (x1, y0, z0), (x0, y0, z0)),
            "+y": ((x1, y1, z1), (x0, y1, z1), (x0, y1, z0), (x1, y1, z0)),
            "-z": ((x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)),
            "+z": ((x0, y1, z1), (x1, y1, z1), (x1, y0, z1), (x0, y0, z1)),
        }
        for name, q in faces.items():
            if name not in skip:
                if yaw:
                    q = turn_about_z(q, ((x0 + x1) / 2, (y0 + y1) / 2), yaw)
                self.quad(*q, mats.get(name, default))

    def wall_x(self, x0, x1, y, thickness, z0, z1, material, openings=()) -> None:
        """A thick wall along x at y (centre), with openings [(xa, xb, za, zb)] cut through it."""
        self._wall(0, x0, x1, y, thickness, z0, z1, material, openings)

    def wall_y(self, y0, y1, x, thickness, z0, z1, material, openings=()) -> None:
        """A thick wall along y at x (centre), with openings [(ya, yb, za, zb)] cut through it."""
        self._wall(1, y0, y1, x, thickness, z0, z1, material, openings)

    def _wall(self, axis, a0, a1, c, th, z0, z1, material, openings) -> None:
        def box(a_lo, a_hi, zl, zh):
            if a_hi - a_lo < 1e-6 or zh - zl < 1e-6:
                return
            if axis == 0:
                self.box((a_lo, c - th / 2, zl), (a_hi, c + th / 2, zh), material)
            else:
                self.box((c - th / 2, a_lo, zl), (c + th / 2, a_hi, zh), material)

        cur = a0
        for (oa, ob, oz0, oz1) in sorted(openings):
            box(cur, oa, z0, z1)
            box(oa, ob, z0, oz0)  # below the opening (windows)
            box(oa, ob, oz1, z1)  # lintel above
            cur = ob
        box(cur, a1, z0, z1)

    def poster(self, centre, normal_axis: str, width: float, height: float, material: str, offset: float = 0.01) -> None:
        """An upright picture on a wall whose inward normal is ``normal_axis`` ('+x','-x','+y','-y')."""
        cx, cy, cz = centre
        sgn = 1.0 if normal_axis[0] == "+" else -1.0
        w, h = width / 2, height / 2
        if normal_axis[1] == "x":
            x = cx + sgn * offset
            # looking at the wall from inside, u runs to the viewer's right
            p0, p1 = (x, cy - sgn * w, cz + h), (x, cy + sgn * w, cz + h)
            p2, p3 = (x, cy + sgn * w, cz - h), (x, cy - sgn * w, cz - h)
        else:
            y = cy + sgn * offset
            p0, p1 = (cx + sgn * w, y, cz + h), (cx - sgn * w, y, cz + h)
            p2, p3 = (cx - sgn * w, y, cz - h), (cx + sgn * w, y, cz - h)
        self.quad(p0, p1, p2, p3, material)

    def build(self) -> Mesh:
        return Mesh(
            np.concatenate(self._v).astype(np.float64),
            np.array(self._f, dtype=np.int32),
            np.array(self._uv, dtype=np.float64),
            np.array(self._m, dtype=np.int32),
            np.array(self._o, dtype=np.int32),
            np.array(self._parents, dtype=np.int32),
        )
