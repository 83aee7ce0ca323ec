"""Scan readers (PLY, E57, LAS/LAZ), the parse cache, decimation and ``cristal scan``: good files and broken ones."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from services.geometry.se3 import Pose
from services.io import scan_cache
from services.io.decimate import random_decimate, voxel_decimate
from services.io.scan import Scan, ScanError
from services.io.scans import load_scan, save_ply, scan_info

pytestmark = pytest.mark.timeout(60)

N = 500
RNG = np.random.default_rng(7)
XYZ = RNG.uniform(-20, 20, (N, 3))
RGB = RNG.integers(0, 256, (N, 3)).astype(np.uint8)


@pytest.fixture(autouse=True)
def _user_cache(tmp_path, monkeypatch):
    """Keep the fallback cache (~/.cache/cristal) inside the test's folder."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user-cache"))


def write_ply(path, xyz=XYZ, colours=None, *, text=False, byte_order="<", xyz_type="f4", comments=()):
    """A PLY via plyfile; ``colours`` is a (N, 3) array written with its own dtype (None: no colour)."""
    from plyfile import PlyData, PlyElement

    fields = [(a, xyz_type) for a in "xyz"]
    if colours is not None:
        fields += [(c, colours.dtype.str[1:]) for c in ("red", "green", "blue")]
    v = np.empty(len(xyz), fields)
    for k, a in enumerate("xyz"):
        v[a] = xyz[:, k]
    if colours is not None:
        for k, c in enumerate(("red", "green", "blue")):
            v[c] = colours[:, k]
    PlyData([PlyElement.describe(v, "vertex")], text=text, byte_order=byte_order, comments=list(comments)).write(str(path))
    return path


def assert_error(path, match, **kw):
    with pytest.raises(ScanError) as e:
        load_scan(path, **kw)
    msg = str(e.value)
    assert str(path) in msg and "\n" not in msg, msg
    assert any(m in msg.lower() for m in ([match] if isinstance(match, str) else match)), msg
    return msg


# ---------------------------------------------------------------- PLY


@pytest.mark.parametrize("text,byte_order", [(False, "<"), (False, ">"), (True, "=")], ids=["binary_le", "binary_be", "ascii"])
@pytest.mark.parametrize("xyz_type", ["f4", "f8"])
def test_ply_encodings_and_coordinate_types(tmp_path, text, byte_order, xyz_type):
    p = write_ply(tmp_path / "s.ply", colours=RGB, text=text, byte_order=byte_order, xyz_type=xyz_type)
    s = load_scan(p)
    assert len(s) == N and s.xyz.dtype == np.float32 and s.rgb.dtype == np.uint8
    np.testing.assert_allclose(s.world_xyz(), XYZ, atol=1e-5)
    np.testing.assert_array_equal(s.rgb, RGB)
    assert s.meta["format"] == "ply" and s.meta["dropped_nonfinite"] == 0 and not s.origin.any()


@pytest.mark.parametrize("kind", ["ushort", "float01", "float255"])
def test_ply_colour_types_scale_to_8_bit(tmp_path, kind):
    colours = {"ushort": RGB.astype(np.uint16) * 257, "float01": RGB.astype(np.float32) / 255,
               "float255": RGB.astype(np.float32)}[kind]
    s = load_scan(write_ply(tmp_path / f"{kind}.ply", colours=colours))
    np.testing.assert_array_equal(s.rgb, RGB)


def test_save_ply_round_trips_points_colours_and_stations(tmp_path):
    stations = [Pose.from_quat_t([0, 0, 0.3826834, 0.9238795], [1, 2, 1.5]), Pose.from_quat_t([0.1, 0, 0, 1], [-4, 0, 2])]
    scan = Scan(XYZ.astype(np.float32), RGB, np.zeros(3), stations)
    for binary in (True, False):
        p = tmp_path / f"rt_{binary}.ply"
        save_ply(scan, p, binary=binary)
        back = load_scan(p, cache=False)
        np.testing.assert_allclose(back.world_xyz(), scan.world_xyz(), atol=1e-6)
        np.testing.assert_array_equal(back.rgb, RGB)
        assert len(back.stations) == 2
        for a, b in zip(back.stations, stations):
            dt, dr = a.distance_to(b)
            assert dt < 1e-6 and dr < 1e-4
    assert b"property float x" in (tmp_path / "rt_True.ply").read_bytes()[:400]


def test_large_coordinates_keep_millimetres_through_the_origin(tmp_path):
    world = np.array([[500000.123, 5600000.456, 312.789]]) + RNG.uniform(0, 50, (N, 3)).round(3)
    p = write_ply(tmp_path / "utm.ply", world, RGB, xyz_type="f8")
    s = load_scan(p)
    assert s.origin.any() and np.all(s.origin == np.round(s.origin))  # whole metres
    assert np.abs(s.world_xyz() - world).max() < 1e-4  # well under a millimetre
    station = Pose.from_quat_t([0, 0, 0.2, 1], [500010.1234, 5600020.5678, 315.0])
    s.stations = [station]
    save_ply(s, tmp_path / "utm_out.ply")  # written as double world coordinates
    assert b"property double x" in (tmp_path / "utm_out.ply").read_bytes()[:600]
    back = load_scan(tmp_path / "utm_out.ply")
    assert np.abs(back.world_xyz() - world).max() < 1e-4
    assert np.abs(back.stations[0].t - station.t).max() < 1e-9
    info = scan_info(s)
    assert info["bounds_min"][0] == pytest.approx(world[:, 0].min(), abs=1e-3)


# ---------------------------------------------------------------- E57


def _write_e57(path, scans):
    """``scans``: list of (local xyz, rgb or None, quaternion w x y z, translation)."""
    import pye57

    with pye57.E57(str(path), mode="w") as e:
        for xyz, rgb, q_wxyz, t in scans:
            data = {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]}
            if rgb is not None:
                data.update(colorRed=rgb[:, 0], colorGreen=rgb[:, 1], colorBlue=rgb[:, 2])
            e.write_scan_raw(data, rotation=np.asarray(q_wxyz, float), translation=np.asarray(t, float))
    return path


def test_e57_two_scans_land_in_the_world_frame(tmp_path):
    a, b = XYZ[:300], XYZ[300:]
    qa, ta = [np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)], [10.0, -3.0, 1.5]  # 45 deg about z
    qb, tb = [np.cos(np.pi / 6), np.sin(np.pi / 6), 0, 0], [-7.0, 4.0, 0.25]  # 60 deg about x
    p = _write_e57(tmp_path / "two.e57", [(a, RGB[:300], qa, ta), (b, RGB[300:], qb, tb)])
    s = load_scan(p)
    Ta = Pose.from_quat_t([*qa[1:], qa[0]], ta)
    Tb = Pose.from_quat_t([*qb[1:], qb[0]], tb)
    expected = np.concatenate([Ta.transform(a), Tb.transform(b)])
    np.testing.assert_allclose(s.world_xyz(), expected, atol=1e-4)  # pye57 stores float32 locally
    np.testing.assert_array_equal(s.rgb, RGB)
    assert len(s.stations) == 2
    assert s.stations[0].distance_to(Ta)[0] < 1e-9 and s.stations[1].distance_to(Tb)[1] < 1e-6
    assert s.meta["format"] == "e57" and s.meta["e57_scans"] == 2
    assert s.meta["station_points"] == [300, len(XYZ) - 300]  # which points each station has (scan check)


def test_e57_without_colour(tmp_path):
    p = _write_e57(tmp_path / "grey.e57", [(XYZ, None, [1, 0, 0, 0], [0, 0, 0])])
    assert_error(p, "no colour")
    s = load_scan(p, require_color=False)
    assert len(s) == N and np.all(s.rgb == 128) and s.meta["has_color"] is False


INTENSITY = np.r_[RNG.uniform(0.0, 1.0, N - 2), 0.0, 1.0]  # a laser's return strength, two points at the extremes


def assert_grey_from(s, intensity):
    """Points grey from ``intensity``: one level per point on all three channels, as a camera would show a surface of
    that reflectance (linear in it up to the 99.5th percentile's white, then a 2.2 gamma), whatever the file's range."""
    assert s.meta["has_color"] is False and s.meta["intensity_grey"] == len(intensity) == len(s)
    assert np.all(s.rgb[:, :1] == s.rgb)
    g = s.rgb[:, 0].astype(float)
    assert np.all(np.diff(g[np.argsort(intensity, kind="stable")]) >= 0)  # monotone in the intensity
    lo = min(0.0, intensity.min())  # (signed values, dB, start at their minimum)
    x = np.clip((intensity - lo) / (np.percentile(intensity, 99.5) - lo), 0, 1)
    assert np.abs(g - 255 * x ** (1 / 2.2)).max() <= 1.5  # a half as reflective surface is 186, not 128
    assert g.min() == 0 and g.max() == 255


def test_e57_intensity_without_colour_becomes_grey(tmp_path):
    fields = {"cartesianX": ("double", XYZ[:, 0]), "cartesianY": ("double", XYZ[:, 1]),
              "cartesianZ": ("double", XYZ[:, 2]), "intensity": (("int", 0, 2047), np.rint(INTENSITY * 2047))}
    p = _write_e57_fields(tmp_path / "intensity.e57", fields, [1, 0, 0, 0], [0, 0, 0])
    s = load_scan(p)  # usable without require_color=False: the intensity gives the renderer something to show
    assert_grey_from(s, INTENSITY)
    assert scan_info(s)["intensity_grey"] == N
    assert_grey_from(load_scan(p), INTENSITY)  # and from the cache
    save_ply(s, tmp_path / "converted.ply")  # (scan convert): the grey levels saved as colour, still told apart
    c = load_scan(tmp_path / "converted.ply")
    np.testing.assert_array_equal(c.rgb, s.rgb)
    assert c.meta["has_color"] is True and c.meta["intensity_grey"] == N


@pytest.mark.parametrize("name,dtype,scale", [("intensity", "f4", 1.0), ("scalar_Intensity", "f4", 2047.0),
                                              ("intensity", "u2", 65535.0), ("reflectance", "f4", -30.0)])
def test_ply_intensity_without_colour_becomes_grey(tmp_path, name, dtype, scale):
    from plyfile import PlyData, PlyElement

    v = np.empty(N, [(a, "f4") for a in "xyz"] + [(name, dtype)])
    for k, a in enumerate("xyz"):
        v[a] = XYZ[:, k]
    v[name] = np.rint(INTENSITY * scale) if dtype[0] == "u" else INTENSITY * scale  # (dB reflectance: negative)
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "i.ply"))
    assert_grey_from(load_scan(tmp_path / "i.ply"), INTENSITY if scale > 0 else -INTENSITY)


def test_e57_scans_with_and_without_colour_mix_colour_and_grey_from_intensity(tmp_path):
    """One station's export with pictures, another's without: each point keeps what its scan has."""
    import pye57

    path = tmp_path / "mixed.e57"
    with pye57.E57(str(path), mode="w") as e:
        e.write_scan_raw({"cartesianX": XYZ[:300, 0], "cartesianY": XYZ[:300, 1], "cartesianZ": XYZ[:300, 2],
                          "colorRed": RGB[:300, 0], "colorGreen": RGB[:300, 1], "colorBlue": RGB[:300, 2]})
        e.write_scan_raw({"cartesianX": XYZ[300:, 0], "cartesianY": XYZ[300:, 1], "cartesianZ": XYZ[300:, 2],
                          "intensity": INTENSITY[300:]})
    s = load_scan(path)
    np.testing.assert_array_equal(s.rgb[:300], RGB[:300])
    assert s.meta["has_color"] is True and s.meta["intensity_grey"] == N - 300
    g = s.rgb[300:, 0]
    assert np.all(s.rgb[300:, :1] == s.rgb[300:]) and g.min() < 30 and g.max() > 225


def test_blank_colour_fields_give_way_to_the_intensity(tmp_path):
    """Exports that wrote colour fields without pictures (every point black, or white) but a real intensity: grey from
    the intensity, in every format; real colours stay colours even where an intensity comes along."""
    import laspy
    from plyfile import PlyData, PlyElement

    white = np.full((N, 3), 255, np.uint8)
    fields = {"cartesianX": ("double", XYZ[:, 0]), "cartesianY": ("double", XYZ[:, 1]),
              "cartesianZ": ("double", XYZ[:, 2]), "colorRed": (("int", 0, 255), np.zeros(N)),
              "colorGreen": (("int", 0, 255), np.zeros(N)), "colorBlue": (("int", 0, 255), np.zeros(N)),
              "intensity": ("double", INTENSITY)}
    assert_grey_from(load_scan(_write_e57_fields(tmp_path / "black.e57", fields, [1, 0, 0, 0], [0, 0, 0])), INTENSITY)
    for name, rgb, grey in (("white", white, True), ("colour", RGB, False)):
        v = np.empty(N, [(a, "f4") for a in "xyz"] + [(c, "u1") for c in ("red", "green", "blue")] + [("intensity", "f4")])
        for k, a in enumerate("xyz"):
            v[a] = XYZ[:, k]
        for k, c in enumerate(("red", "green", "blue")):
            v[c] = rgb[:, k]
        v["intensity"] = INTENSITY
        PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / f"{name}.ply"))
        s = load_scan(tmp_path / f"{name}.ply")
        if grey:
            assert_grey_from(s, INTENSITY)
        else:
            np.testing.assert_array_equal(s.rgb, RGB)
            assert s.meta["has_color"] is True and s.meta["intensity_grey"] == 0
    las = laspy.create(point_format=3, file_version="1.2")
    las.header.offsets, las.header.scales = np.floor(XYZ.min(axis=0)), np.array([0.001, 0.001, 0.001])
    las.x, las.y, las.z = XYZ[:, 0], XYZ[:, 1], XYZ[:, 2]
    las.red = las.green = las.blue = np.zeros(N, np.uint16)
    las.intensity = np.rint(INTENSITY * 65535).astype(np.uint16)
    las.write(str(tmp_path / "black.las"))
    assert_grey_from(load_scan(tmp_path / "black.las"), INTENSITY)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_intensity_without_colour_becomes_grey(tmp_path, suffix):
    import laspy

    las = laspy.create(point_format=1, file_version="1.2")  # no colour
    las.header.offsets, las.header.scales = np.floor(XYZ.min(axis=0)), np.array([0.001, 0.001, 0.001])
    las.x, las.y, las.z = XYZ[:, 0], XYZ[:, 1], XYZ[:, 2]
    las.intensity = np.rint(INTENSITY * 65535).astype(np.uint16)
    las.write(str(tmp_path / f"i{suffix}"))
    assert_grey_from(load_scan(tmp_path / f"i{suffix}"), INTENSITY)
    for value in (0, 1000):  # a writer that left the field empty, or filled it with one value: no grey to take
        las.intensity = np.full(N, value, np.uint16)
        las.write(str(tmp_path / f"flat{value}{suffix}"))
        assert_error(tmp_path / f"flat{value}{suffix}", "no colour")
        assert np.all(load_scan(tmp_path / f"flat{value}{suffix}", require_color=False).rgb == 128)


def _write_e57_fields(path, fields, q_wxyz, t, colour_max=None):
    """One E57 scan written with libE57 directly (pye57's writer only does float cartesian, 8-bit colour).

    ``fields``: name -> (node, values) with node "double", ("int", lo, hi) or ("scaled", lo, hi, scale).
    """
    import pye57
    from pye57 import libe57

    with pye57.E57(str(path), mode="w") as e:
        imf = e.image_file
        scan, pose, rot, tr, proto = (libe57.StructureNode(imf) for _ in range(5))
        scan.set("guid", libe57.StringNode(imf, "{cristal-test}"))
        if colour_max:
            lim = libe57.StructureNode(imf)
            for c in ("Red", "Green", "Blue"):
                lim.set(f"color{c}Minimum", libe57.IntegerNode(imf, 0))
                lim.set(f"color{c}Maximum", libe57.IntegerNode(imf, colour_max))
            scan.set("colorLimits", lim)
        for k, v in zip("wxyz", q_wxyz):
            rot.set(k, libe57.FloatNode(imf, float(v)))
        for k, v in zip("xyz", t):
            tr.set(k, libe57.FloatNode(imf, float(v)))
        pose.set("rotation", rot)
        pose.set("translation", tr)
        scan.set("pose", pose)
        for name, (node, _) in fields.items():
            proto.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE) if node == "double" else
                      libe57.IntegerNode(imf, node[1], node[1], node[2]) if node[0] == "int" else
                      libe57.ScaledIntegerNode(imf, 0, node[1], node[2], node[3], 0.0))
        points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
        scan.set("points", points)
        e.data3d.append(scan)
        arrays = {k: np.ascontiguousarray(v, np.float64) for k, (_, v) in fields.items()}  # float64 buffers convert
        bufs = libe57.VectorSourceDestBuffer()
        for k, a in arrays.items():
            bufs.append(libe57.SourceDestBuffer(imf, k, a, len(a), True, True))
        writer = points.writer(bufs)
        writer.write(len(next(iter(arrays.values()))))
        writer.close()
    return path


def test_e57_spherical_16_bit_colour_and_invalid_points(tmp_path):
    rae = np.column_stack([RNG.uniform(1, 30, N), RNG.uniform(-np.pi, np.pi, N), RNG.uniform(-1.2, 1.2, N)])
    invalid = np.zeros(N)
    invalid[[0, 5, 99]] = 2
    q, t = [np.cos(0.4), 0, 0, np.sin(0.4)], [100.0, 200.0, 3.0]
    fields = {"sphericalRange": ("double", rae[:, 0]), "sphericalAzimuth": ("double", rae[:, 1]),
              "sphericalElevation": ("double", rae[:, 2]), "sphericalInvalidState": (("int", 0, 2), invalid)}
    fields.update({f"color{c}": (("int", 0, 65535), RGB[:, k] * 257.0) for k, c in enumerate(("Red", "Green", "Blue"))})
    s = load_scan(_write_e57_fields(tmp_path / "sph.e57", fields, q, t, colour_max=65535))
    keep = invalid == 0
    r, az, el = rae[keep].T
    local = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    np.testing.assert_allclose(s.world_xyz(), Pose.from_quat_t([0, 0, q[3], q[0]], t).transform(local), atol=1e-5)
    np.testing.assert_array_equal(s.rgb, RGB[keep])
    assert s.meta["dropped_invalid"] == 3 and len(s) == N - 3
    assert s.meta["station_points"] == [N - 3]  # counted after the invalid points went


def test_e57_scaled_integer_coordinates(tmp_path):
    xyz = RNG.uniform(-50, 50, (N, 3)).round(3)
    fields = {f"cartesian{a}": (("scaled", -10**6, 10**6, 0.001), xyz[:, k]) for k, a in enumerate("XYZ")}
    fields.update({f"color{c}": (("int", 0, 255), RGB[:, k]) for k, c in enumerate(("Red", "Green", "Blue"))})
    s = load_scan(_write_e57_fields(tmp_path / "si.e57", fields, [1, 0, 0, 0], [0.5, 0, 0]))
    np.testing.assert_allclose(s.world_xyz(), xyz + [0.5, 0, 0], atol=1e-6)
    np.testing.assert_array_equal(s.rgb, RGB)


# ---------------------------------------------------------------- LAS / LAZ


def _write_las(path, xyz, rgb16):
    import laspy

    las = laspy.create(point_format=3, file_version="1.2")
    las.header.offsets = np.floor(xyz.min(axis=0))
    las.header.scales = np.array([0.001, 0.001, 0.001])
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    las.write(str(path))
    return path


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("bits", [16, 8])
def test_las_and_laz_with_rgb(tmp_path, suffix, bits):
    world = XYZ + [650000.0, 4200000.0, 50.0]
    rgb = RGB.astype(np.uint16) * 256 if bits == 16 else RGB.astype(np.uint16)
    p = _write_las(tmp_path / f"s{suffix}", world, rgb)
    import laspy

    with laspy.open(str(p)) as f:
        assert f.header.are_points_compressed == (suffix == ".laz")
    s = load_scan(p)
    assert np.abs(s.world_xyz() - world).max() < 1e-3 + 1e-6  # LAS stores millimetres
    np.testing.assert_array_equal(s.rgb, RGB)
    assert s.meta["format"] == "las"


# ---------------------------------------------------------------- broken input


def test_missing_file_and_unknown_suffix(tmp_path):
    assert_error(tmp_path / "nope.ply", "no such file")
    (tmp_path / "cloud.xyz").write_text("1 2 3\n")
    assert_error(tmp_path / "cloud.xyz", "unknown scan format")


def test_truncated_binary_ply(tmp_path):
    p = write_ply(tmp_path / "cut.ply", colours=RGB)
    p.write_bytes(p.read_bytes()[:-1000])
    assert_error(p, "truncated")


def test_ply_without_colours(tmp_path):
    p = write_ply(tmp_path / "nocolour.ply")
    assert_error(p, "no colour")
    s = load_scan(p, require_color=False)
    assert np.all(s.rgb == 128)
    assert_error(p, "no colour")  # also when the (colourless) result comes from the cache


def test_ply_missing_coordinates(tmp_path):
    from plyfile import PlyData, PlyElement

    v = np.zeros(3, [("x", "f4"), ("y", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "xy.ply"))
    assert_error(tmp_path / "xy.ply", "no z coordinate")


def test_nonfinite_points_are_dropped_and_counted(tmp_path, caplog):
    xyz = XYZ.copy()
    xyz[[3, 10, 11]] = np.nan
    xyz[20, 1] = np.inf
    xyz[21, 2] = -np.inf
    s = load_scan(write_ply(tmp_path / "nan.ply", xyz, RGB, xyz_type="f8"))
    keep = np.isfinite(xyz).all(axis=1)
    assert len(s) == N - 5 and s.meta["dropped_nonfinite"] == 5
    np.testing.assert_allclose(s.world_xyz(), xyz[keep], atol=1e-5)
    np.testing.assert_array_equal(s.rgb, RGB[keep])
    assert "dropped 5 non-finite" in caplog.text
    assert load_scan(tmp_path / "nan.ply").meta["dropped_nonfinite"] == 5  # kept in the cache


def test_empty_clouds(tmp_path):
    assert_error(write_ply(tmp_path / "empty.ply", XYZ[:0], RGB[:0]), "no points")
    msg = assert_error(write_ply(tmp_path / "allnan.ply", np.full((4, 3), np.nan), RGB[:4]), "no points")
    assert "4 non-finite" in msg


@pytest.mark.parametrize("suffix", [".ply", ".e57", ".las", ".laz"])
def test_garbage_bytes_give_a_clear_error(tmp_path, suffix):
    p = tmp_path / f"garbage{suffix}"
    p.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    msg = assert_error(p, ["corrupt", "truncated"])
    assert "Traceback" not in msg


def test_truncated_las(tmp_path):
    p = _write_las(tmp_path / "cut.las", XYZ, RGB.astype(np.uint16) * 256)
    p.write_bytes(p.read_bytes()[:-200])
    assert_error(p, ["truncated", "corrupt"])


# ---------------------------------------------------------------- cache


def test_cache_hit_then_invalidated_by_touch_and_rewrite(tmp_path):
    p = write_ply(tmp_path / "c.ply", colours=RGB)
    first = load_scan(p)
    assert first.meta["from_cache"] is False and (tmp_path / "c.ply.cristal-cache" / "xyz.npy").is_file()
    second = load_scan(p)
    assert second.meta["from_cache"] is True and not second.xyz.flags.writeable  # memory-mapped
    np.testing.assert_array_equal(second.xyz, first.xyz)
    np.testing.assert_array_equal(second.rgb, first.rgb)

    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # touch: same bytes, new mtime
    assert load_scan(p).meta["from_cache"] is False
    assert load_scan(p).meta["from_cache"] is True

    write_ply(p, XYZ[:100], RGB[:100])  # rewritten with other content
    s = load_scan(p)
    assert s.meta["from_cache"] is False and len(s) == 100
    assert load_scan(p, cache=False).meta["from_cache"] is False


def test_corrupt_cache_is_reparsed_and_rewritten(tmp_path):
    p = write_ply(tmp_path / "c.ply", colours=RGB)
    load_scan(p)
    (tmp_path / "c.ply.cristal-cache" / "xyz.npy").write_bytes(b"not an npy file")
    s = load_scan(p)
    assert s.meta["from_cache"] is False and len(s) == N
    assert load_scan(p).meta["from_cache"] is True
    meta = json.loads((tmp_path / "c.ply.cristal-cache" / "meta.json").read_text())
    assert meta["points"] == N and meta["source_size"] == p.stat().st_size


def test_cache_falls_back_to_user_cache_when_folder_not_writable(tmp_path, monkeypatch):
    real = scan_cache._write_dir

    def refuse_beside(d, scan, meta):
        if d.name.endswith(scan_cache.CACHE_SUFFIX):
            raise PermissionError(13, "Permission denied", str(d.parent))
        return real(d, scan, meta)

    monkeypatch.setattr(scan_cache, "_write_dir", refuse_beside)
    p = write_ply(tmp_path / "ro.ply", colours=RGB)
    load_scan(p)
    assert not (tmp_path / "ro.ply.cristal-cache").exists()
    s = load_scan(p)
    assert s.meta["from_cache"] is True and str(tmp_path / "user-cache" / "cristal") in s.meta["cache_dir"]


# ---------------------------------------------------------------- decimation


def _grid_scan():
    xyz = RNG.uniform(0, 10, (20000, 3)).astype(np.float32)
    return Scan(xyz, RNG.integers(0, 256, (20000, 3)), np.array([1000.0, 2000.0, 0.0]), [Pose.identity()])


def test_random_decimate_exact_and_deterministic():
    s = _grid_scan()
    a, b, c = random_decimate(s, 0.1234), random_decimate(s, 0.1234), random_decimate(s, 0.1234, seed=1)
    assert len(a) == round(0.1234 * len(s))
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert not np.array_equal(a.xyz, c.xyz)
    assert len(random_decimate(s, 1.0)) == len(s)
    assert np.array_equal(a.origin, s.origin) and len(a.stations) == 1
    with pytest.raises(ScanError):
        random_decimate(s, 0.0)


def test_voxel_decimate_one_point_per_voxel_with_mean_colour():
    s = _grid_scan()
    v = voxel_decimate(s, 1.0)
    q = np.floor(s.xyz - s.xyz.min(axis=0)).astype(int)
    occupied = {tuple(r) for r in q}
    assert len(v) == len(occupied)
    vq = np.floor(v.xyz - s.xyz.min(axis=0)).astype(int)
    assert len({tuple(r) for r in vq}) == len(v)  # one point per voxel, each from its own voxel
    # each kept point is a real point, the one nearest its voxel mean; colour is the voxel mean
    k = tuple(vq[0])
    members = np.all(q == k, axis=1)
    mean = s.xyz[members].astype(np.float64).mean(axis=0)
    nearest = s.xyz[members][np.argmin(((s.xyz[members] - mean) ** 2).sum(axis=1))]
    np.testing.assert_array_equal(v.xyz[0], nearest)
    np.testing.assert_array_equal(v.rgb[0], np.rint(s.rgb[members].mean(axis=0)).astype(np.uint8))
    np.testing.assert_array_equal(voxel_decimate(s, 1.0).xyz, v.xyz)  # deterministic
    assert np.array_equal(v.origin, s.origin)


# ---------------------------------------------------------------- CLI


def test_cli_scan_info_and_convert(tmp_path, capsys):
    from services.cli import main

    p = write_ply(tmp_path / "s.ply", colours=RGB)
    assert main(["scan", "info", str(p)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["points"] == N and summary["from_cache"] is False and summary["has_color"] is True
    assert summary["upright"] is None  # no stations in the file: nothing to tell it by
    assert main(["scan", "info", str(p)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["from_cache"] is True

    out = tmp_path / "small.ply"
    assert main(["scan", "convert", str(p), str(out), "--fraction", "0.5"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["points_out"] == N // 2
    assert len(load_scan(out)) == N // 2


def test_cli_scan_info_on_bad_files_exits_2(tmp_path, capsys):
    from services.cli import main

    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\x00")
    assert main(["scan", "info", str(bad)]) == 2
    assert main(["scan", "info", str(tmp_path / "missing.e57")]) == 2
    assert main(["scan", "convert", str(bad), str(tmp_path / "out.txt")]) == 2
