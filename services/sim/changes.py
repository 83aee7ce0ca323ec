"""The site on the camera's day is not the site the scanner saw: furniture moved, stock picked, boxes left about.

A scan is made once; cameras come for weeks after. ``change_scene`` takes the scene as scanned and returns the mesh
the camera films: ``fraction`` of its movable objects (``MeshBuilder.movable``: desks, chairs, shelf boxes, pallets
with their load) changed, and new boxes standing on the floor.

- An object on the floor is moved (two in three: 0.15-0.6 m along the floor, turned up to 30 degrees about the
  vertical) or taken away; one raised off the floor (a box on a shelf, a pallet in a rack) slides 0.05-0.2 m and
  turns up to 10 degrees, or is taken away (one in two). What rests on an object (a desk's monitor) goes with it.
- New boxes, a third as many as the objects changed (at least one), 0.3-0.8 m wide and 0.3-1 m high, in materials
  the site already has.

Nothing is moved onto the camera's route, nor put there: a footprint keeps ``clearance_m`` from the route's polyline
(the walk's spline keeps close to it), or where it stood closer, no closer than that. Deterministic from ``rng``.
"""

from __future__ import annotations

import numpy as np

from services.sim.mesh import Mesh, MeshBuilder, turn_about_z
from services.sim.scenes import Scene

__all__ = ["change_scene"]

_NEW_MATERIALS = ("cardboard", "fabric", "blue_metal", "orange_metal", "wood")


def _route_distance(xy: np.ndarray, route: list[np.ndarray]) -> np.ndarray:
    """Distance (N,) in the floor plane from points (N, 2) to the route's polyline."""
    pts = np.asarray([p[:2] for p in route], float)
    out = np.full(len(xy), np.inf)
    for a, b in zip(pts[:-1], pts[1:]):
        ab = b - a
        s = np.clip(((xy - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        out = np.minimum(out, np.linalg.norm(xy - (a + s[:, None] * ab), axis=1))
    return out


def _gap(v: np.ndarray, route: list[np.ndarray]) -> float:
    """How close a footprint (the object's vertices) comes to the route (a 5 x 5 grid over its bounds: boxes)."""
    lo, hi = v[:, :2].min(0), v[:, :2].max(0)
    xs, ys = np.linspace(lo[0], hi[0], 5), np.linspace(lo[1], hi[1], 5)
    return float(_route_distance(np.array([(x, y) for x in xs for y in ys]), route).min())


def change_scene(scene: Scene, fraction: float, rng: np.random.Generator,
                 clearance_m: float = 0.6) -> tuple[Mesh, dict]:
    """The mesh the camera films, and what changed: {"movable", "moved", "removed", "added"}."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"the share of objects changed must be within 0..1 (got {fraction})")
    mesh = scene.mesh
    obj = mesh.object_ids()
    ids = np.unique(obj[obj >= 0])
    if fraction > 0 and len(ids) == 0:
        raise ValueError(f"scene {scene.name!r} has no movable objects to change")
    vertices = mesh.vertices.copy()
    keep = np.ones(mesh.n_faces, bool)
    moved = removed = 0
    chosen = ids[rng.random(len(ids)) < fraction]
    parents = mesh.object_parents()
    gone: set[int] = set()
    for k in chosen:  # (ascending: an object before what rests on it)
        if int(k) in gone:
            continue
        # the object with what rests on it (a desk's monitor)
        group = {int(k)}
        for j in range(int(k) + 1, len(parents)):
            if parents[j] in group:
                group.add(j)
        faces = np.flatnonzero(np.isin(obj, list(group)))
        vi = np.unique(mesh.faces[faces])
        v = vertices[vi]
        on_floor = v[:, 2].min() < 0.02
        if rng.random() < (1 / 3 if on_floor else 1 / 2):
            keep[faces] = False
            gone |= group
            removed += 1
            continue
        centre = 0.5 * (v[:, :2].min(0) + v[:, :2].max(0))
        clear = min(clearance_m, _gap(v, scene.route))
        for _ in range(10):
            dist = rng.uniform(0.15, 0.6) if on_floor else rng.uniform(0.05, 0.2)
            ang = rng.uniform(0, 2 * np.pi)
            yaw = np.radians(rng.uniform(-30, 30) if on_floor else rng.uniform(-10, 10))
            nv = turn_about_z(v, centre, yaw, dist * np.array([np.cos(ang), np.sin(ang)]))
            if _gap(nv, scene.route) >= clear:
                vertices[vi] = nv
                moved += 1
                break
        else:  # nowhere to put it off the route: taken away
            keep[faces] = False
            gone |= group
            removed += 1

    # new boxes on the floor
    n_new = max(1, int(round(len(chosen) / 3))) if fraction > 0 else 0
    (x0, y0, _), (x1, y1, _) = scene.bounds
    b = MeshBuilder(rng)
    added = 0
    for _ in range(n_new):
        for _ in range(200):
            w, d, h = rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8), rng.uniform(0.3, 1.0)
            cx, cy = rng.uniform(x0 + 0.5, x1 - 0.5), rng.uniform(y0 + 0.5, y1 - 0.5)
            corners = np.array([[cx - w / 2, cy - d / 2, 0.0], [cx + w / 2, cy + d / 2, h]])
            if _gap(corners, scene.route) >= clearance_m + 0.4:
                with b.movable():
                    b.box(corners[0], corners[1], str(rng.choice(_NEW_MATERIALS)), yaw=rng.uniform(0, np.pi / 2))
                added += 1
                break

    faces = mesh.faces[keep]
    parts_v, parts_f, parts_uv = [vertices], [faces], [mesh.uv[keep]]
    parts_m, parts_o, parts_p = [mesh.material[keep]], [obj[keep]], [parents]
    if added:
        new = b.build()
        parts_v.append(new.vertices)
        parts_f.append(new.faces + len(vertices))
        parts_uv.append(new.uv)
        parts_m.append(new.material)
        parts_o.append(new.object_ids() + len(parents))
        parts_p.append(np.full(added, -1, np.int32))
    out = Mesh(np.concatenate(parts_v), np.concatenate(parts_f).astype(np.int32), np.concatenate(parts_uv),
               np.concatenate(parts_m).astype(np.int32), np.concatenate(parts_o).astype(np.int32),
               np.concatenate(parts_p).astype(np.int32))
    return out, {"fraction": fraction, "movable": int(len(ids)), "moved": moved, "removed": removed, "added": added}
