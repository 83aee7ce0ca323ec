"""Ground-truth appearance of a simulated site: trace rays, sample mip-mapped textures, light them.

``SceneRenderer`` holds a scene's BVH and textures and answers two questions:
``render(T_wc, camera, lighting)`` (linear radiance + z-depth of a pinhole/distorted camera) and
``cast(origins, dirs, lighting)`` (radiance + range along arbitrary rays, for the LiDAR).
Lighting is Lambert + Blinn-Phong from point lights with inverse-square falloff, no shadows;
highlights depend on the viewer, so the scan's colours and a camera's colours differ as in life.
"""

from __future__ import annotations

from functools import lru_cache

import numba as nb
import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.sim.materials import MaterialLibrary
from services.sim.mesh import Mesh
from services.sim.raytrace import build_bvh, trace
from services.sim.scenes import Lighting

__all__ = ["SceneRenderer"]


@nb.njit(cache=True, inline="always")
def _bilinear(buf, off, size, u, v):
    """Bilinear texture lookup with repeat wrap; texel centres at (i + 0.5) / size. Returns (r, g, b)."""
    fu = (u - np.floor(u)) * size - 0.5
    fv = (v - np.floor(v)) * size - 0.5
    i0 = int(np.floor(fu))
    j0 = int(np.floor(fv))
    au = fu - i0
    av = fv - j0
    i1 = (i0 + 1) % size
    j1 = (j0 + 1) % size
    i0 = i0 % size
    j0 = j0 % size
    b00 = off + (j0 * size + i0) * 3
    b01 = off + (j0 * size + i1) * 3
    b10 = off + (j1 * size + i0) * 3
    b11 = off + (j1 * size + i1) * 3
    w00 = (1 - au) * (1 - av)
    w01 = au * (1 - av)
    w10 = (1 - au) * av
    w11 = au * av
    r = w00 * buf[b00] + w01 * buf[b01] + w10 * buf[b10] + w11 * buf[b11]
    g = w00 * buf[b00 + 1] + w01 * buf[b01 + 1] + w10 * buf[b10 + 1] + w11 * buf[b11 + 1]
    b = w00 * buf[b00 + 2] + w01 * buf[b01 + 2] + w10 * buf[b10 + 2] + w11 * buf[b11 + 2]
    return r, g, b


@nb.njit(cache=True, parallel=True)
def _shade(orig, dirs, t, tri, bu, bv, spread, uv, mat, normals, uvdens, tex, offs, tex_size, n_levels,
           spec_w, shin, lights, ambient, out):
    n = dirs.shape[0]
    for r in nb.prange(n):
        f = tri[r]
        if f < 0:
            out[r, 0] = 0.0
            out[r, 1] = 0.0
            out[r, 2] = 0.0
            continue
        dl = np.sqrt(dirs[r, 0] ** 2 + dirs[r, 1] ** 2 + dirs[r, 2] ** 2)
        dx, dy, dz = dirs[r, 0] / dl, dirs[r, 1] / dl, dirs[r, 2] / dl
        dist = t[r] * dl
        px = orig[r, 0] + dirs[r, 0] * t[r]
        py = orig[r, 1] + dirs[r, 1] * t[r]
        pz = orig[r, 2] + dirs[r, 2] * t[r]
        nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
        cosv = nx * dx + ny * dy + nz * dz
        if cosv > 0:  # double-sided: face the viewer
            nx, ny, nz = -nx, -ny, -nz
            cosv = -cosv
        cosv = -cosv
        w0 = 1.0 - bu[r] - bv[r]
        u = w0 * uv[f, 0, 0] + bu[r] * uv[f, 1, 0] + bv[r] * uv[f, 2, 0]
        v = w0 * uv[f, 0, 1] + bu[r] * uv[f, 1, 1] + bv[r] * uv[f, 2, 1]
        m = mat[f]
        # mip level from the pixel footprint in texels
        foot = dist * spread[r] / max(cosv, 0.2) * uvdens[f] * tex_size
        lvl = np.log2(max(foot, 1.0))
        l0 = min(int(lvl), n_levels - 1)
        l1 = min(l0 + 1, n_levels - 1)
        a = min(lvl - l0, 1.0)
        r0, g0, b0 = _bilinear(tex, offs[m, l0], tex_size >> l0, u, v)
        r1, g1, b1 = _bilinear(tex, offs[m, l1], tex_size >> l1, u, v)
        alb0 = (1 - a) * r0 + a * r1
        alb1 = (1 - a) * g0 + a * g1
        alb2 = (1 - a) * b0 + a * b1
        e0, e1, e2 = ambient[0], ambient[1], ambient[2]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for li in range(lights.shape[0]):
            lx = lights[li, 0] - px
            ly = lights[li, 1] - py
            lz = lights[li, 2] - pz
            d2 = lx * lx + ly * ly + lz * lz
            ld = np.sqrt(d2)
            lx /= ld
            ly /= ld
            lz /= ld
            ndl = nx * lx + ny * ly + nz * lz
            if ndl <= 0:
                continue
            att = 1.0 / (d2 + lights[li, 6] ** 2)
            e0 += lights[li, 3] * ndl * att
            e1 += lights[li, 4] * ndl * att
            e2 += lights[li, 5] * ndl * att
            if spec_w[m] > 0:
                hx, hy, hz = lx - dx, ly - dy, lz - dz
                hn = np.sqrt(hx * hx + hy * hy + hz * hz)
                ndh = max(0.0, (nx * hx + ny * hy + nz * hz) / hn)
                sp = spec_w[m] * ndh ** shin[m] * att * 0.25
                s0 += lights[li, 3] * sp
                s1 += lights[li, 4] * sp
                s2 += lights[li, 5] * sp
        out[r, 0] = alb0 * e0 + s0
        out[r, 1] = alb1 * e1 + s1
        out[r, 2] = alb2 * e2 + s2


@lru_cache(maxsize=8)
def _pixel_rays(camera: Camera) -> np.ndarray:
    return camera.pixel_rays().reshape(-1, 3)


class SceneRenderer:
    """Ray-traced ground truth for one scene. Build once (BVH, textures), render many times."""

    def __init__(self, mesh: Mesh, texture_seed: int = 0):
        self.mesh = mesh
        self.bvh = build_bvh(mesh.vertices, mesh.faces)
        self.lib = MaterialLibrary(texture_seed)
        self.normals = np.ascontiguousarray(mesh.face_normals())
        self.uvdens = np.ascontiguousarray(mesh.uv_density())
        self.uv = np.ascontiguousarray(mesh.uv)
        self.mat = np.ascontiguousarray(mesh.material.astype(np.int32))

    def cast(self, origins: np.ndarray, dirs: np.ndarray, lighting: Lighting, spread: float | np.ndarray = 1e-3,
             tmax: float = 1e9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Radiance (N,3) linear, distance along ``dirs`` in units of |dir| (inf on miss), and triangle id."""
        dirs = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
        origins = np.require(np.broadcast_to(np.asarray(origins, np.float64), dirs.shape), None, ["C", "W"])
        t, tri, u, v = trace(self.bvh, origins, dirs, tmax=tmax)
        sp = np.ascontiguousarray(np.broadcast_to(np.asarray(spread, np.float64), (len(dirs),)))
        out = np.empty((len(dirs), 3))
        _shade(origins, dirs, t, tri, u, v, sp, self.uv, self.mat, self.normals, self.uvdens, self.lib.buffer,
               self.lib.offsets, self.lib.tex_size, self.lib.n_levels, self.lib.specular, self.lib.shininess,
               np.ascontiguousarray(lighting.lights, np.float64), np.ascontiguousarray(lighting.ambient, np.float64), out)
        return out, t, tri

    def render_rows(self, row_poses: list[Pose], camera: Camera, lighting: Lighting) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`render`, each image row seen from its own camera-to-world pose (a rolling shutter); the depth of
        a row is along its own camera's z."""
        H, W = camera.height, camera.width
        if len(row_poses) != H:
            raise ValueError(f"{len(row_poses)} row poses for an image {H} rows high")
        rays_c = _pixel_rays(camera).reshape(H, W, 3)
        R = np.stack([T.R for T in row_poses])  # (H, 3, 3)
        dirs = np.einsum("hwj,hij->hwi", rays_c, R).reshape(-1, 3)
        return self._image(np.repeat(np.stack([T.t for T in row_poses]), W, axis=0), dirs, camera, lighting)

    def render(self, T_wc: Pose, camera: Camera, lighting: Lighting) -> tuple[np.ndarray, np.ndarray]:
        """(H,W,3) float32 linear radiance and (H,W) float32 z-depth (0 where nothing is hit) for ``T_wc``."""
        return self._image(T_wc.t, _pixel_rays(camera) @ T_wc.R.T, camera, lighting)

    def _image(self, origins: np.ndarray, dirs: np.ndarray, camera: Camera, lighting: Lighting) -> tuple[np.ndarray, np.ndarray]:
        """Radiance and z-depth images of one ray per pixel (``dirs`` rotated from pixel rays with z = 1, so the
        distance along them is the z-depth)."""
        rad, t, _ = self.cast(origins, dirs, lighting, 1.0 / max(camera.fx, camera.fy))
        depth = np.where(np.isfinite(t), t, 0.0)
        H, W = camera.height, camera.width
        return rad.reshape(H, W, 3).astype(np.float32), depth.reshape(H, W).astype(np.float32)
