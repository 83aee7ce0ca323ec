"""Simulated sites: an office of two rooms joined by a doorway, and a 60 x 40 m warehouse with shelf rows.

Each preset is a function of a seed returning a ``Scene``: the textured mesh, the light
sets at scan time and at camera time (deliberately different), the scanner stations,
and a route for hand-held camera walks (waypoints through free space and points of
interest the operator looks at). World frame: metres, z up, origin at a floor corner.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.sim.mesh import Mesh, MeshBuilder

__all__ = ["Scene", "Lighting", "PRESETS", "make_scene"]


@dataclass
class Lighting:
    """Point lights (N, 7): x y z, linear r g b power, softening radius (m); plus an ambient term."""

    lights: np.ndarray
    ambient: np.ndarray  # (3,)

    def to_dict(self) -> dict:
        return {"lights": self.lights.tolist(), "ambient": self.ambient.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Lighting":
        return cls(np.asarray(d["lights"], np.float64).reshape(-1, 7), np.asarray(d["ambient"], np.float64))


@dataclass
class Scene:
    name: str
    mesh: Mesh
    scan_lighting: Lighting
    camera_lighting: Lighting
    stations: np.ndarray  # (S, 3) scanner centres
    route: list[np.ndarray]  # waypoints (x, y) the camera walks through, in order
    pois: np.ndarray  # (P, 3) points of interest the operator looks at
    height_range: tuple[float, float] = (1.35, 1.7)  # camera heights
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0, 0, 0), (1, 1, 1))
    info: dict = field(default_factory=dict)


def _ceiling_lights(xs, ys, z, colour, power, rng, off_prob=0.0) -> list[list[float]]:
    out = []
    for x in xs:
        for y in ys:
            p = power * rng.uniform(0.85, 1.15) * (0.0 if rng.random() < off_prob else 1.0)
            out.append([x, y, z, colour[0] * p, colour[1] * p, colour[2] * p, 0.4])
    return out


def office(seed: int) -> Scene:
    """Two rooms (6 x 5 m each, 2.8 m high) side by side, a 0.9 m doorway in the partition wall."""
    rng = np.random.default_rng(seed)
    b = MeshBuilder(rng)
    H, T = 2.8, 0.15
    XA0, XA1 = 0.0, 6.0  # room A
    XB0, XB1 = XA1 + T, XA1 + T + 6.0  # room B
    Y1 = 5.0
    door_y = float(rng.uniform(1.4, 2.6))
    # floors, ceiling
    b.quad((XA0, 0, 0), (XA1, 0, 0), (XA1, Y1, 0), (XA0, Y1, 0), "carpet")
    b.quad((XA1, 0, 0), (XB1, 0, 0), (XB1, Y1, 0), (XA1, Y1, 0), "floor_tiles")
    b.quad((XA0, Y1, H), (XB1, Y1, H), (XB1, 0, H), (XA0, 0, H), "ceiling")
    # outer walls (thick) and the partition with its doorway
    b.wall_x(XA0 - T, XB1 + T, -T / 2, T, 0, H, "painted_wall")
    b.wall_x(XA0 - T, XB1 + T, Y1 + T / 2, T, 0, H, "painted_wall", openings=[(8.0, 9.4, 0.9, 2.2)])
    b.wall_y(0, Y1, XA0 - T / 2, T, 0, H, "painted_wall")
    b.wall_y(0, Y1, XB1 + T / 2, T, 0, H, "brick_wall")
    b.wall_y(0, Y1, XA1 + T / 2, T, 0, H, "painted_wall", openings=[(door_y, door_y + 0.9, 0.0, 2.1)])
    # a window in room B's north wall shows "outside": a grass/gravel backdrop 3 m away
    b.quad((7.0, Y1 + 3, 0), (10.4, Y1 + 3, 0), (10.4, Y1 + 3, 3.5), (7.0, Y1 + 3, 3.5), "grass_mat")
    b.quad((7.0, Y1 + 0.2, 0.0), (10.4, Y1 + 0.2, 0.0), (10.4, Y1 + 3, 0.0), (7.0, Y1 + 3, 0.0), "gravel")

    posters = ["poster_astronaut", "poster_coffee", "poster_chelsea", "poster_rocket", "poster_hubble",
               "poster_coins", "poster_camera", "poster_text"]
    rng.shuffle(posters)
    pois = []

    def poster(c, axis, w, h, m):
        b.poster(c, axis, w, h, m)
        pois.append(c)

    # room A: whiteboard on the west wall, posters south and north
    b.poster((XA0, 2.5, 1.5), "+x", 2.0, 1.1, "whiteboard")
    pois.append((XA0, 2.5, 1.5))
    poster((1.6, 0.0, 1.6), "+y", 1.0, 0.75, posters[0])
    poster((4.3, 0.0, 1.5), "+y", 0.8, 1.0, posters[1])
    poster((2.0, Y1, 1.55), "-y", 1.2, 0.8, posters[2])
    poster((4.6, Y1, 1.6), "-y", 0.7, 0.7, posters[3])
    poster((XA1, 0.8, 1.6), "-x", 0.6, 0.8, posters[4])
    # room B: posters east (brick) and south, a shelf unit north-west
    poster((XB1, 1.3, 1.6), "-x", 1.0, 0.7, posters[5])
    poster((XB1, 3.8, 1.5), "-x", 0.8, 1.0, posters[6])
    poster((9.5, 0.0, 1.6), "+y", 1.4, 0.9, posters[7])
    poster((XB0, 4.3, 1.5), "+x", 0.7, 0.9, "poster_astronaut")

    # furniture, room A: desks in the middle, cabinets along walls
    for (x, y) in [(2.2, 2.0), (3.9, 3.2)]:
        x += rng.uniform(-0.2, 0.2)
        with b.movable():
            b.box((x - 0.8, y - 0.4, 0.72), (x + 0.8, y + 0.4, 0.76), "wood")
            for dx in (-0.75, 0.75):
                for dy in (-0.35, 0.35):
                    b.box((x + dx - 0.03, y + dy - 0.03, 0), (x + dx + 0.03, y + dy + 0.03, 0.72), "dark_plastic")
            with b.movable():  # on the desk
                b.box((x - 0.25, y - 0.15, 0.76), (x + 0.25, y - 0.12, 1.1), "dark_plastic")  # monitor
        with b.movable():
            b.box((x - 0.3, y + 0.45, 0.0), (x + 0.3, y + 1.0, 0.48), "fabric")  # chair seat
            b.box((x - 0.3, y + 0.95, 0.48), (x + 0.3, y + 1.0, 1.0), "fabric")  # chair back
        pois.append((x, y, 0.9))
    with b.movable():
        b.box((0.05, 4.3, 0), (1.2, 4.9, 1.9), {"default": "blue_metal", "+y": "blue_metal"})
    with b.movable():
        b.box((5.3, 0.05, 0), (5.95, 1.2, 1.2), "wood")
        with b.movable():  # on the cabinet
            b.box((5.4, 0.2, 1.2), (5.8, 0.6, 1.45), "cardboard")
    # room B: a metal shelf with boxes, a sofa, a table
    sx0, sx1 = XB0 + 0.2, XB0 + 2.6
    for z in (0.05, 0.7, 1.35, 2.0):
        b.box((sx0, Y1 - 0.6, z), (sx1, Y1 - 0.05, z + 0.04), "orange_metal")
        if z < 2.0:
            x = sx0 + 0.05
            while x < sx1 - 0.4:
                w = rng.uniform(0.3, 0.6)
                h = rng.uniform(0.25, 0.55)
                if x + w < sx1:
                    with b.movable():
                        b.box((x, Y1 - 0.55, z + 0.04), (x + w, Y1 - 0.12, z + 0.04 + h), "cardboard")
                x += w + rng.uniform(0.03, 0.15)
    for x in (sx0, sx1 - 0.05):
        b.box((x, Y1 - 0.6, 0), (x + 0.05, Y1 - 0.05, 2.1), "blue_metal")
    pois.append(((sx0 + sx1) / 2, Y1 - 0.3, 1.2))
    with b.movable():  # the sofa
        b.box((9.0, 0.3, 0), (11.2, 1.1, 0.45), "fabric")
        b.box((9.0, 0.1, 0), (11.2, 0.3, 0.9), "fabric")
    with b.movable():  # the table
        b.box((9.4, 2.0, 0.7), (10.8, 3.0, 0.74), "wood")
        b.box((9.5, 2.1, 0), (9.56, 2.16, 0.7), "dark_plastic")
        b.box((10.64, 2.84, 0), (10.7, 2.9, 0.7), "dark_plastic")
        with b.movable():  # on the table
            b.box((10.0, 2.3, 0.74), (10.4, 2.6, 1.0), "cardboard")
    pois.append((10.1, 2.5, 0.8))
    pois.append((8.7, Y1, 1.5))  # the window

    xs = [1.5, 4.5]
    ys = [1.25, 3.75]
    scan_lights = _ceiling_lights(xs, ys, H - 0.1, (1.0, 0.92, 0.78), 6.0, rng) + \
        _ceiling_lights([XB0 + 1.5, XB0 + 4.5], ys, H - 0.1, (1.0, 0.92, 0.78), 6.0, rng)
    cam_lights = _ceiling_lights(xs, ys, H - 0.1, (0.85, 0.92, 1.0), 4.5, rng, off_prob=0.25) + \
        _ceiling_lights([XB0 + 1.5, XB0 + 4.5], ys, H - 0.1, (0.85, 0.92, 1.0), 5.0, rng, off_prob=0.25)
    cam_lights.append([8.7, Y1 + 1.5, 2.0, 9.0, 9.5, 10.0, 1.0])  # daylight through the window

    ya, yb = float(rng.uniform(1.2, 1.8)), float(rng.uniform(3.2, 3.9))
    door_mid = door_y + 0.45
    route = [
        (1.3, ya), (3.0, yb), (4.8, door_mid), (XA1 + T / 2, door_mid), (7.3, door_mid),
        (9.0, 3.8), (11.0, 2.0), (8.5, 1.6), (7.2, door_mid), (XA1 + T / 2, door_mid), (4.6, door_mid), (2.0, 3.0),
    ]
    return Scene(
        name="office",
        mesh=b.build(),
        scan_lighting=Lighting(np.array(scan_lights), np.array([0.06, 0.06, 0.055])),
        camera_lighting=Lighting(np.array(cam_lights), np.array([0.08, 0.085, 0.095])),
        stations=np.array([[2.9, 2.6, 1.5], [9.1, 2.4, 1.5], [XA1 - 1.0, door_mid + 1.2, 1.3]]),
        route=[np.array(p, dtype=np.float64) for p in route],
        pois=np.array(pois, dtype=np.float64),
        bounds=((XA0 - T, -T, 0.0), (XB1 + T, Y1 + T, H)),
        info={"door_y": door_y},
    )


def warehouse(seed: int) -> Scene:
    """A 60 x 40 m hall, 8 m high, with rows of pallet racks and cross aisles."""
    rng = np.random.default_rng(seed)
    b = MeshBuilder(rng)
    X, Y, H, T = 60.0, 40.0, 8.0, 0.3
    b.quad((0, 0, 0), (X, 0, 0), (X, Y, 0), (0, Y, 0), "concrete_floor")
    b.quad((0, Y, H), (X, Y, H), (X, 0, H), (0, 0, H), "blue_metal")
    for (wall, args) in (("x", (-T, X + T, -T / 2)), ("x", (-T, X + T, Y + T / 2)), ("y", (0, Y, -T / 2)), ("y", (0, Y, X + T / 2))):
        fn = b.wall_x if wall == "x" else b.wall_y
        fn(*args, T, 0, 3.0, "brick_wall")
        fn(*args, T, 3.0, H, "painted_wall")
    pois = []
    posters = ["poster_astronaut", "poster_coffee", "poster_chelsea", "poster_rocket", "poster_hubble", "poster_coins",
               "poster_camera", "poster_text"]
    for i, x in enumerate(np.linspace(5, 55, 8)):
        b.poster((x, 0.0, 2.0), "+y", 2.0, 1.4, posters[i % len(posters)])
        b.poster((x, Y, 2.0), "-y", 2.0, 1.4, posters[(i + 3) % len(posters)])
        pois += [(x, 0.0, 2.0), (x, Y, 2.0)]
    for i, y in enumerate((10.0, 30.0)):
        b.poster((0.0, y, 2.2), "+x", 2.4, 1.6, "whiteboard")
        b.poster((X, y, 2.2), "-x", 2.4, 1.6, posters[(i + 5) % len(posters)])
        pois += [(0.0, y, 2.2), (X, y, 2.2)]

    # racks: rows along x, in two blocks separated by a cross aisle at x ~ 30
    depth, bay, levels = 1.1, 2.7, (0.0, 1.6, 3.2, 4.8)
    row_ys = [5.0, 6.2] + [5.0 + k * 5.0 + d for k in range(1, 6) for d in (0.0, 1.2)]
    row_ys = [y for y in row_ys if y + depth < Y - 4.0]
    blocks = [(6.0, 27.0), (33.0, 54.0)]
    for y0 in row_ys:
        for (xa, xb) in blocks:
            nb_ = int((xb - xa) // bay)
            for k in range(nb_ + 1):
                x = xa + k * bay
                b.box((x, y0, 0), (x + 0.1, y0 + depth, 6.2), "orange_metal")
            for z in levels[1:]:
                b.box((xa, y0, z - 0.12), (xa + nb_ * bay + 0.1, y0 + 0.08, z), "shelf_labels")
                b.box((xa, y0 + depth - 0.08, z - 0.12), (xa + nb_ * bay + 0.1, y0 + depth, z), "blue_metal")
            for k in range(nb_):
                for z in levels:
                    if rng.random() < 0.15:
                        continue  # empty slot: lets the scanner see through, like real racks
                    for s in range(2):
                        px = xa + k * bay + 0.2 + s * 1.25
                        with b.movable():  # a pallet with its load
                            b.box((px, y0 + 0.05, z + 0.01), (px + 1.1, y0 + depth - 0.05, z + 0.15), "pallet_wood")
                            cx = px + 0.05
                            while cx < px + 1.0:
                                w = rng.uniform(0.3, 0.55)
                                h = rng.uniform(0.3, 1.2)
                                if cx + w <= px + 1.1:
                                    b.box((cx, y0 + 0.1, z + 0.15), (cx + w, y0 + depth - 0.1, z + 0.15 + h),
                                          "cardboard" if rng.random() < 0.8 else "fabric")
                                cx += w + 0.04
            pois.append(((xa + xb) / 2, y0, 2.0))
    # free-standing pallets and a machine near the walls
    for _ in range(10):
        x, y = rng.uniform(3, 57), rng.uniform(35.5, 38.5)
        with b.movable():
            b.box((x, y, 0), (x + 1.2, y + 1.0, 0.15), "pallet_wood")
            b.box((x + 0.1, y + 0.1, 0.15), (x + 1.1, y + 0.9, 0.15 + rng.uniform(0.4, 1.5)), "cardboard")
        pois.append((x + 0.6, y + 0.5, 0.8))

    xs = np.arange(5.0, X, 10.0)
    ys = np.arange(5.0, Y, 10.0)
    scan_lights = _ceiling_lights(xs, ys, H - 0.3, (1.0, 0.95, 0.85), 90.0, rng)
    cam_lights = _ceiling_lights(xs, ys, H - 0.3, (0.9, 0.95, 1.0), 70.0, rng, off_prob=0.2)
    aisle_y = [row_ys[i] + depth + 0.0 for i in range(1, len(row_ys), 2)]
    aisle_centres = [(a + c) / 2 for a, c in zip(aisle_y, [y for y in row_ys[2::2]])]
    a1 = aisle_centres[0] if aisle_centres else 10.0
    a2 = aisle_centres[1] if len(aisle_centres) > 1 else 15.0
    route = [(8.0, a1), (16.0, a1 + rng.uniform(-0.3, 0.3)), (24.0, a1), (30.0, a1), (30.0, (a1 + a2) / 2), (30.0, a2),
             (36.0, a2), (44.0, a2 + rng.uniform(-0.3, 0.3)), (52.0, a2)]
    stations = [[30.0, 3.0, 1.6], [30.0, Y - 3.0, 1.6], [3.0, Y / 2, 1.6], [X - 3.0, Y / 2, 1.6]]
    for c in aisle_centres:
        stations += [[16.5, c, 1.6], [43.5, c, 1.6]]
    for cy in (2.5, Y - 2.5):
        stations += [[12.0, cy, 1.6], [48.0, cy, 1.6]]
    return Scene(
        name="warehouse",
        mesh=b.build(),
        scan_lighting=Lighting(np.array(scan_lights), np.array([0.05, 0.05, 0.05])),
        camera_lighting=Lighting(np.array(cam_lights), np.array([0.07, 0.075, 0.08])),
        stations=np.array(stations, dtype=np.float64),
        route=[np.array(p, dtype=np.float64) for p in route],
        pois=np.array(pois, dtype=np.float64),
        height_range=(1.4, 1.8),
        bounds=((-T, -T, 0.0), (X + T, Y + T, H)),
        info={"aisles": aisle_centres},
    )


PRESETS = {"office": office, "warehouse": warehouse}


def make_scene(preset: str, seed: int) -> Scene:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[preset](seed)
