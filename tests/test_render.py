"""The neural point renderer: splat against brute force, CPU vs torch, the depth filter on a planted
leak, hole filling against simulator ground truth, and back-projection onto the true surfaces."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from services.geometry.camera import Camera
from services.geometry.se3 import Pose, look_at
from services.io.scan import Scan
from services.render.cloud import prepare_cloud
from services.render.depth_filter import hierarchical_depth_filter
from services.render.splat import SplatConfig, splat
from services.render.splat_torch import DeviceCloud, splat_torch

CAM_D = Camera(80, 60, 50.0, 52.0, 39.2, 30.1, (-0.12, 0.03, 0.001, -0.001, 0.0))


def brute_force_splat(scan, T_wc, cam, delta=0.02):
    Xc = T_wc.inverse().transform(scan.world_xyz())
    m = Xc[:, 2] >= 0.05
    uv, z = cam.project(Xc[m])
    col = scan.rgb[m].astype(np.float64)
    px = np.floor(uv + 0.5).astype(int)
    ok = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    px, z, col = px[ok], z[ok], col[ok]
    zmin = np.full((cam.height, cam.width), np.inf)
    np.minimum.at(zmin, (px[:, 1], px[:, 0]), z)
    sel = z <= zmin[px[:, 1], px[:, 0]] + delta
    acc = np.zeros((cam.height, cam.width, 3))
    cnt = np.zeros((cam.height, cam.width))
    np.add.at(acc, (px[sel, 1], px[sel, 0]), col[sel])
    np.add.at(cnt, (px[sel, 1], px[sel, 0]), 1)
    return acc / np.maximum(cnt, 1)[..., None], np.where(np.isfinite(zmin), zmin, 0), cnt


def random_room(n=60000, seed=0, origin=(500000.0, 5600000.0, 100.0)):
    rng = np.random.default_rng(seed)
    # points on the walls of a 6 x 5 x 3 room plus clutter, far from the origin (survey coordinates)
    face = rng.integers(0, 6, n)
    p = rng.uniform([0, 0, 0], [6, 5, 3], (n, 3))
    for f, (ax, v) in enumerate([(0, 0), (0, 6), (1, 0), (1, 5), (2, 0), (2, 3)]):
        p[face == f, ax] = v
    p[: n // 5] = rng.uniform([2, 2, 0], [4, 3, 1.5], (n // 5, 3))
    return Scan(p.astype(np.float32), rng.integers(0, 256, (n, 3), dtype=np.uint8), np.asarray(origin))


def test_splat_equals_brute_force_with_distortion():
    scan = random_room()
    T_wc = Pose(look_at((1, 1, 1.5), (5, 4, 1.2)).R, scan.origin + [1, 1, 1.5])
    r = splat(prepare_cloud(scan, chunk=1024), T_wc, CAM_D, SplatConfig(lod_points_per_px=0))  # every point
    rgb, depth, cnt = brute_force_splat(scan, T_wc, CAM_D)
    assert (cnt > 0).mean() > 0.5
    same = np.isclose(r.depth, depth, atol=1e-4)
    assert same.mean() > 0.998  # float32 vs float64 may round a point onto the neighbouring pixel
    assert np.abs(r.rgb - rgb)[same].max() < 1e-3 or (np.abs(r.rgb - rgb)[same] > 1e-3).mean() < 0.002
    assert (r.count == cnt).mean() > 0.998


def test_the_splat_kernel_compiles_once_whatever_the_pose_and_camera():
    """A pose inverted by transposing R is Fortran-ordered, one built from a 4x4 is a view, a distortion tuple is
    float64: each new argument layout would make numba compile the kernel again, 7-14 s on a 2-core box, which a
    server paid on its first client's relocalization (a missed deadline; CI failed on it)."""
    from services.render import splat as splat_mod

    scan = random_room(20000)
    cloud = prepare_cloud(scan, chunk=1024)
    R = look_at((1, 1, 1.5), (5, 4, 1.2)).R
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, scan.origin + [1, 1, 1.5]
    poses = [Pose(R, scan.origin + [1, 1, 1.5]), Pose(np.asfortranarray(R), scan.origin + [1, 1, 1.5]),
             Pose(M[:3, :3], M[:3, 3]), Pose(R.astype(np.float32), (scan.origin + [1, 1, 1.5]).astype(np.float32))]
    cams = [CAM_D, Camera(64, 48, 40.0, 40.0, 32.0, 24.0), Camera.from_fov(64, 48, 60.0)]
    for T in poses:
        for cam in cams:
            assert splat(cloud, T, cam).count.sum() > 0
    assert len(splat_mod._splat.signatures) == 1  # (also over every render the test session made before this one)


def test_rendering_leaves_torch_on_the_threads_it_was_given():
    """numba's OpenMP pool shares torch's runtime, and each parallel launch (and starting the pool) set the
    calling thread's count to all cores: the CLIs' torch.set_num_threads(1) held only until the first render,
    and XFeat's output then depended on whether a render order was computed before it (a database built from
    a freshly parsed scan differed from one built from the scan cache)."""
    from services.render.cloud import render_order

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        scan = random_room(20000, seed=3)
        render_order(scan.xyz)
        assert torch.get_num_threads() == 1
        cloud = prepare_cloud(scan, chunk=1024)
        assert splat(cloud, Pose(look_at((1, 1, 1.5), (5, 4, 1.2)).R, scan.origin + [1, 1, 1.5]), CAM_D).count.sum() > 0
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_frustum_culling_changes_nothing():
    scan = random_room(seed=1)
    cloud = prepare_cloud(scan, chunk=512)
    T_wc = Pose(look_at((0.5, 0.5, 1.0), (6, 0.5, 1.0)).R, scan.origin + [0.5, 0.5, 1.0])
    a, b = splat(cloud, T_wc, CAM_D), splat(cloud, T_wc, CAM_D, cull=False)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.rgb, b.rgb)


def test_numba_and_torch_splats_agree():
    scan = random_room(seed=2)
    T_wc = Pose(look_at((3, 0.5, 1.5), (3, 5, 1.0)).R, scan.origin + [3, 0.5, 1.5])
    r = splat(prepare_cloud(scan), T_wc, CAM_D)
    dc = DeviceCloud(prepare_cloud(scan), "cpu")
    assert dc.bytes_per_point() == 16  # the scan on the device: float32 xyz + rgba
    rgb_t, depth_t, cnt_t = splat_torch(dc, T_wc, CAM_D, chunk=10000)
    same = np.isclose(r.depth, depth_t.numpy(), atol=1e-4)
    assert same.mean() > 0.998
    assert np.abs(r.rgb - rgb_t.numpy())[same].mean() < 0.05


def dense_wall(n=2_000_000, seed=0):
    """A 4 x 3 m wall at x = 6 sampled every ~2.4 mm (a survey scan at short range), coloured by a smooth ramp."""
    rng = np.random.default_rng(seed)
    y, z = rng.uniform(-2, 2, n), rng.uniform(0, 3, n)
    xyz = np.column_stack([np.full(n, 6.0) + rng.normal(0, 0.001, n), y, z]).astype(np.float32)
    rgb = np.column_stack([(y + 2) * 60, z * 80, np.full(n, 100)]).astype(np.uint8)
    return Scan(xyz, rgb, np.array([1000.0, 2000.0, 10.0]))


def test_level_of_detail_splats_a_few_points_per_pixel_and_the_same_image():
    scan = dense_wall()
    cam = Camera.from_fov(160, 120, 60)
    T_wc = Pose(look_at((0, 0, 1.5), (6, 0, 1.5)).R, scan.origin + [0, 0, 1.5])
    cloud = prepare_cloud(scan)
    full = splat(cloud, T_wc, cam, SplatConfig(lod_points_per_px=0))
    lod = splat(cloud, T_wc, cam, SplatConfig(lod_points_per_px=4))
    seen = full.count > 0
    assert full.count[seen].mean() > 50, "the test needs many points per pixel"
    assert lod.count[seen].mean() < 0.25 * full.count[seen].mean()  # most points never touched
    assert (lod.count[seen] > 0).mean() > 0.99  # but (almost) no pixel left empty
    both = seen & (lod.count > 0)
    assert np.abs(lod.depth - full.depth)[both].max() < 0.01
    assert np.abs(lod.rgb - full.rgb)[both].mean() < 2.0
    # from 0.5 m away the wall puts a few points on each pixel: level of detail keeps every one
    T_near = Pose(look_at((5.5, 0, 1.5), (6, 0, 1.5)).R, scan.origin + [5.5, 0, 1.5])
    a, b = splat(cloud, T_near, cam, SplatConfig(lod_points_per_px=0)), splat(cloud, T_near, cam, SplatConfig(lod_points_per_px=4))
    assert b.count.sum() >= 0.95 * a.count.sum()


def test_level_of_detail_picks_the_same_points_in_torch():
    scan = dense_wall(400_000, seed=1)
    cam = Camera.from_fov(160, 120, 60)
    T_wc = Pose(look_at((0, 0.3, 1.4), (6, 0, 1.5)).R, scan.origin + [0, 0.3, 1.4])
    cloud = prepare_cloud(scan)
    cfg = SplatConfig(lod_points_per_px=2)
    r = splat(cloud, T_wc, cam, cfg)
    rgb_t, depth_t, cnt_t = splat_torch(DeviceCloud(cloud, "cpu"), T_wc, cam, cfg, chunk=50000)
    assert r.count.sum() < 0.5 * splat(cloud, T_wc, cam, SplatConfig(lod_points_per_px=0)).count.sum()
    assert (cnt_t.numpy() == r.count).mean() > 0.998
    same = np.isclose(r.depth, depth_t.numpy(), atol=1e-4)
    assert same.mean() > 0.998


def test_filter_removes_background_behind_wall_but_keeps_wall_and_doorway():
    rng = np.random.default_rng(0)
    # a wall at x = 2 sampled on a 4 cm grid (gaps at close range), with a 1 m doorway; a dense wall behind at x = 8
    gy, gz = np.meshgrid(np.arange(-3, 3, 0.04), np.arange(0, 3, 0.04))
    wall = np.column_stack([np.full(gy.size, 2.0), gy.ravel(), gz.ravel()])
    door = (np.abs(wall[:, 1]) < 0.5) & (wall[:, 2] < 2.1)
    wall = wall[~door]
    back = np.column_stack([np.full(400000, 8.0), rng.uniform(-8, 8, 400000), rng.uniform(0, 3, 400000)])
    xyz = np.vstack([wall, back]).astype(np.float32)
    rgb = np.vstack([np.full((len(wall), 3), 200), np.full((len(back), 3), 40)]).astype(np.uint8)
    cam = Camera.from_fov(320, 240, 80)
    T_wc = look_at((0.9, 0, 1.3), (2, 0, 1.3))
    r = splat(prepare_cloud(Scan(xyz, rgb)), T_wc, cam)
    keep = hierarchical_depth_filter(torch.from_numpy(r.depth)).numpy()
    # truth per pixel: is the ray inside the doorway?
    rays = cam.pixel_rays() @ T_wc.R.T
    hit = T_wc.t + rays * ((2.0 - T_wc.t[0]) / rays[..., :1])
    in_door = (np.abs(hit[..., 1]) < 0.45) & (hit[..., 2] < 2.05)
    leak = (r.depth > 3.0) & ~in_door
    wall_px = (r.depth > 0) & (r.depth < 3.0)
    assert leak.sum() > 0.05 * (r.depth > 0).sum(), "the test needs a leaky splat"
    # within one coarse pixel (16 px at 4 levels) of the doorway's edge the filter, by design, trusts the far side
    import cv2

    dist = cv2.distanceTransform((~in_door).astype(np.uint8), cv2.DIST_L2, 5)
    far = leak & (dist > 24)
    assert far.sum() > 0.3 * leak.sum()
    assert (far & keep).sum() < 0.01 * far.sum(), "background behind the wall must be removed"
    assert (leak & keep).sum() < 0.35 * leak.sum()
    assert (wall_px & keep).sum() > 0.97 * wall_px.sum(), "the wall itself must stay"
    door_bg = (r.depth > 3.0) & in_door
    assert (door_bg & keep).sum() > 0.9 * door_bg.sum(), "background seen through the doorway must stay"


@pytest.fixture(scope="module")
def site_renderer(small_site):
    from services.io.scans import load_scan
    from services.render.renderer import Renderer
    from services.sim.site import SimSite

    out, _, _ = small_site
    return Renderer(load_scan(out / "scan.ply")), SimSite(out), out


def test_unet_improves_ssim_and_filter_cuts_leakage_on_held_out_views(site_renderer):
    from services.io.sequence import open_sequence
    from services.render.quality import leakage, ssim

    renderer, site, out = site_renderer
    seq = open_sequence(out / "seq_00")
    cam = Camera.from_fov(320, 240, 70)  # another camera than the sequence's
    s_filter, s_full, leak_raw, leak_filt = [], [], [], []
    for i in (0, 4, 8, 11):
        T_wc = seq.groundtruth.poses[i]
        gt, gt_depth = site.render(T_wc, cam)
        raw = renderer.render(T_wc, cam, "splat")
        filt = renderer.render(T_wc, cam, "filter")
        full = renderer.render(T_wc, cam, "full")
        s_filter.append(ssim(filt.rgb, gt))
        s_full.append(ssim(full.rgb, gt))
        leak_raw.append(leakage(raw.depth, gt_depth))
        leak_filt.append(leakage(filt.depth, gt_depth))
        np.testing.assert_array_equal(full.measured, filt.measured)
        assert (full.depth_filled > 0).all()
    assert np.mean(s_full) > np.mean(s_filter) + 0.05, (s_full, s_filter)
    assert np.mean(leak_filt) < 0.4 * np.mean(leak_raw), (leak_filt, leak_raw)  # a sparse 0.6-degree scan: ~3x here


def test_measured_depth_backprojects_onto_true_surfaces(site_renderer):
    from services.io.sequence import open_sequence

    renderer, site, out = site_renderer
    seq = open_sequence(out / "seq_00")
    T_wc = seq.groundtruth.poses[5]
    r = renderer.render(T_wc, seq.camera)  # the sequence's distorted camera
    _, gt_depth = site.render(T_wc, seq.camera)
    v, u = np.nonzero(r.measured)
    X, ok = r.backproject(np.column_stack([u, v]).astype(float))
    assert ok.all()
    z_true = gt_depth[v, u]
    z_est = T_wc.inverse().transform(X)[:, 2]
    err = np.abs(z_est - z_true) / z_true
    assert np.median(err) < 0.01 and np.mean(err < 0.05) > 0.97


def test_grow_colours_closes_gaps_between_points_only():
    from services.render.grow import _grow_numba, _grow_torch, grow_colours

    H, W = 48, 64
    v, u = np.mgrid[0:H, 0:W]
    rgb = torch.zeros(1, 3, H, W)
    rgb[0, 2] = 1.0  # a blue surface ...
    pts = (u % 4 == 0) & (v % 2 == 0) & (u < 32)  # ... scanned in columns 4 px apart, on the left half only
    mask = torch.from_numpy(pts.astype(np.float32))[None, None]
    before = mask.clone()
    c, m = grow_colours(rgb, mask, 3)
    assert torch.equal(mask, before)  # the caller's mask is not touched
    assert bool(m[0, 0, :, :32].all())  # the gaps between the columns are closed ...
    assert torch.allclose(c[0, :, :, :32], rgb[0, :, :, :32])  # ... with the surface's colour
    assert not bool(m[0, 0, :, 36:].any())  # nothing grows beyond the radius
    c2, m2 = _grow_torch(rgb, mask, 3)  # the CUDA path's steps, here on the CPU
    assert torch.equal(m2, m) and torch.allclose(c2, c, atol=1e-6)
    assert torch.equal(_grow_numba(rgb, mask, 3)[1], m)


def _edge_shift_rms(picture: np.ndarray, truth: np.ndarray, truth_depth: np.ndarray) -> float:
    """RMS displacement (pixels, across the edge) of ``picture``'s texture edges from ``truth``'s: dense optical flow
    at the strongest tenth of the truth's gradients, away from depth edges."""
    import cv2

    a, b = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (truth, picture))
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None)
    gx, gy = (cv2.Sobel(a.astype(np.float32), cv2.CV_32F, dx, 1 - dx, ksize=3) for dx in (1, 0))
    g = np.hypot(gx, gy)
    d = np.where(truth_depth > 0, truth_depth, 1e3)
    flat = cv2.dilate(d, np.ones((5, 5))) / cv2.erode(d, np.ones((5, 5))) < 1.1
    m = (g > np.percentile(g, 90)) & flat
    m[:8], m[-8:], m[:, :8], m[:, -8:] = False, False, False, False
    shift = (flow[..., 0] * gx + flow[..., 1] * gy)[m] / g[m]
    return float(np.sqrt(np.mean(shift ** 2)))


def test_a_supersampled_render_keeps_the_depth_and_draws_edges_where_the_scene_has_them(site_renderer):
    """Supersampled (Render & Match's keyframes), a render keeps the plain render's measured depth, pixel for pixel,
    and its picture's edges sit closer to the simulator's own picture of the scene: points are placed within a
    quarter of a pixel instead of half, and a pixel on an edge takes the share of each side."""
    from services.io.sequence import open_sequence

    renderer, site, out = site_renderer
    seq = open_sequence(out / "seq_00")
    cam = Camera.from_fov(160, 120, 70)  # the scan's points ~1 px apart
    plain, fine = [], []
    for i in (0, 4, 8, 11):
        T_wc = seq.groundtruth.poses[i]
        truth, truth_depth = site.render(T_wc, cam)
        r1 = renderer.render(T_wc, cam)
        r2 = renderer.render(T_wc, cam, supersample=2)
        assert (r1.measured == r2.measured).mean() > 0.999
        both = r1.measured & r2.measured
        assert np.abs(r1.depth[both] - r2.depth[both]).max() < 1e-4
        plain.append(_edge_shift_rms(r1.rgb, truth, truth_depth))
        fine.append(_edge_shift_rms(r2.rgb, truth, truth_depth))
    assert np.mean(fine) < 0.7 * np.mean(plain), (fine, plain)  # 0.09 against 0.18 px when written
    with pytest.raises(ValueError, match="whole number"):
        renderer.render(seq.groundtruth.poses[0], cam, supersample=1.5)


def test_supersampled_pooling_is_the_same_on_both_paths():
    from services.render.supersample import _block_min_nb, _block_min_torch, _pool_numba, _pool_torch

    rng = np.random.default_rng(0)
    H, W, k = 30, 40, 2
    fine_depth = np.where(rng.random((H * k, W * k)) < 0.3, rng.uniform(1, 3, (H * k, W * k)), 0).astype(np.float32)
    rgb = torch.from_numpy(rng.uniform(0, 255, (H * k, W * k, 3)).astype(np.float32))
    depth = torch.from_numpy(_block_min_nb(fine_depth, k))  # the CPU path's kernels against the CUDA path's steps
    assert torch.equal(depth, _block_min_torch(torch.from_numpy(fine_depth), k))
    blocks = fine_depth.reshape(H, k, W, k).transpose(0, 2, 1, 3).reshape(H, W, k * k)
    nearest = np.where(blocks > 0, blocks, np.inf).min(-1)
    np.testing.assert_array_equal(depth.numpy(), np.where(np.isfinite(nearest), nearest, 0))
    depth[:5] = 0  # dropped by the filter: no colour from there
    c, m = _pool_numba(rgb, torch.from_numpy(fine_depth), depth, k, 0.02, 0.0, 2)
    c2, m2 = _pool_torch(rgb, torch.from_numpy(fine_depth), depth, k, 0.02, 0.0, 2)
    assert torch.equal(m, m2) and torch.allclose(c, c2, atol=1e-6)
    assert not bool(m[0, 0, :4].any()) and bool(m[0, 0, 5:].all())  # grown across gaps, not into dropped pixels


def test_plane_depth_interpolates_planes_and_refuses_edges():
    from services.render.depth_sampling import plane_depth, support_fraction

    H, W = 60, 80
    v, u = np.mgrid[0:H, 0:W].astype(float)
    slanted = 1.0 / (0.5 + 0.004 * u - 0.002 * v)  # a plane seen obliquely: inverse depth is affine in (u, v)
    sparse = np.where((u % 4 == 0) & (v % 4 == 0), slanted, 0.0)  # points 4 px apart, as a sparse scan renders
    uv = np.array([[21.3, 17.8], [42.5, 30.1], [60.9, 44.4]])
    z, ok = plane_depth(sparse, uv, radius=4)
    assert ok.all()
    np.testing.assert_allclose(z, 1.0 / (0.5 + 0.004 * uv[:, 0] - 0.002 * uv[:, 1]), rtol=1e-9)
    assert support_fraction(sparse > 0, 0) == pytest.approx(1 / 16) and support_fraction(sparse[:57, :77] > 0, 2) == 1.0
    # a depth edge (a box 30 cm in front of the plane) inside the window: no depth rather than a mix
    edge = np.where(u < 40, sparse, 0.7 * sparse)
    _, ok = plane_depth(edge, np.array([[39.6, 30.0], [20.0, 30.0]]), radius=4)
    assert ok.tolist() == [False, True]
    # points on one side only (the border of a surface): no extrapolation
    half = np.where(u <= 40, sparse, 0.0)
    _, ok = plane_depth(half, np.array([[42.0, 30.0], [38.5, 30.0]]), radius=4)
    assert ok.tolist() == [False, True]
    assert [len(x) for x in plane_depth(sparse, np.zeros((0, 2)), return_plane=True)] == [0, 0, 0]  # a view with no keypoints


def test_invented_near_flags_made_up_colours_not_a_sparse_scan():
    from services.render.depth_sampling import invented_near

    H, W = 60, 80
    v, u = np.mgrid[0:H, 0:W]
    measured = (u % 2 == 0) & (v % 2 == 0)  # a scan sampled every other pixel: gaps, nothing made up
    measured[20:40, 50:70] = False  # a part the scanner never saw: 20 px across, filled by the renderer
    uv = np.array([[10.0, 10.0], [45.0, 30.0], [60.0, 30.0], [35.0, 30.0], [75.0, 55.0]])
    near = invented_near(measured, uv, radius=8, gap_px=2.0)
    assert near.tolist() == [False, True, True, False, False]  # 5 px and inside the hole; 15 px away and beyond
    assert invented_near(measured, np.zeros((0, 2)), 8, 2.0).shape == (0,)


def test_plane_depth_backprojects_sparse_renders_onto_true_surfaces(site_renderer):
    """A scan decimated to 3 % renders mostly holes; depth interpolated between its points is still the
    surface's (simulator ground truth) wherever plane_depth gives one."""
    from services.io.decimate import random_decimate
    from services.io.scans import load_scan
    from services.io.sequence import open_sequence
    from services.render.depth_sampling import plane_depth
    from services.render.renderer import Renderer

    renderer, site, out = site_renderer
    seq = open_sequence(out / "seq_00")
    T_wc = seq.groundtruth.poses[5]
    sparse = Renderer(random_decimate(load_scan(out / "scan.ply"), 0.03), device="cpu")
    cam = seq.camera.scaled(0.5)
    r = sparse.render(T_wc, cam)
    _, gt_depth = site.render(T_wc, cam)
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (2000, 2))
    z, ok = plane_depth(r.depth, uv, radius=4)
    px = np.round(uv).astype(int)
    z_true = gt_depth[px[:, 1], px[:, 0]]
    ok &= z_true > 0
    assert r.hole_fraction > 0.6 and ok.mean() > 1.2 * (1 - r.hole_fraction)  # more than the measured pixels
    err = np.abs(z[ok] - z_true[ok]) / z_true[ok]  # z_true at the nearest pixel centre: a little slack
    assert np.median(err) < 0.01 and np.mean(err < 0.05) > 0.97


def test_cubemap_faces_cover_all_directions(site_renderer):
    from services.render.renderer import cubemap_poses

    poses = cubemap_poses([3, 2.5, 1.4])
    dirs = np.array([T.R[:, 2] for T in poses])
    np.testing.assert_allclose(np.abs(dirs).sum(0), [2, 2, 2])
    for T in poses:
        np.testing.assert_allclose(np.linalg.det(T.R), 1.0)
    renderer, _, _ = site_renderer
    faces = renderer.cubemap([3.0, 2.5, 1.4], size=64)
    assert len(faces) == 6 and all(f.rgb.shape == (64, 64, 3) for f in faces)
    assert np.mean([f.measured.mean() for f in faces]) > 0.3


def test_render_cli_compare(small_site, tmp_path, capsys):
    from services.cli import main

    out, _, _ = small_site
    cam = Camera.from_fov(160, 120, 70)
    cam.save(tmp_path / "cam.json")
    rc = main(["render", str(out / "scan.ply"), "--pose", "3 2.5 1.5 -0.5 0.5 -0.5 0.5", "--camera",
               str(tmp_path / "cam.json"), "--out", str(tmp_path / "r.png"), "--depth", str(tmp_path / "d.npy"),
               "--compare", str(out)])
    assert rc == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["ssim"] > 0.3 and (tmp_path / "r_compare.png").exists()
    assert np.load(tmp_path / "d.npy").shape == (120, 160)
    assert main(["render", str(out / "scan.ply"), "--pose", "nope", "--camera", str(tmp_path / "cam.json"),
                 "--out", str(tmp_path / "x.png")]) == 2


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_and_cuda_renders_agree(site_renderer):
    from services.render.renderer import Renderer

    renderer, site, out = site_renderer
    from services.io.scans import load_scan

    gpu = Renderer(load_scan(out / "scan.ply"), device="cuda")
    cam = Camera.from_fov(320, 240, 70)
    T_wc = look_at((3, 2.5, 1.5), (0, 2.5, 1.4))
    a, b = renderer.render(T_wc, cam), gpu.render(T_wc, cam)
    assert (a.measured == b.measured).mean() > 0.998
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean() < 1.0


def test_render_order_is_kept_with_the_scan_cache_and_survives_a_bad_file(tmp_path, caplog):
    from services.io.scans import load_scan, save_ply

    save_ply(random_room(30000, seed=4), tmp_path / "room.ply")
    scan = load_scan(tmp_path / "room.ply")
    first = prepare_cloud(scan, chunk=1024)
    kept = list(Path(scan.meta["cache_dir"]).glob("render-order-*.npy"))
    assert len(kept) == 1
    again = prepare_cloud(load_scan(tmp_path / "room.ply"), chunk=1024)  # from the kept order: the same cloud
    np.testing.assert_array_equal(first.xyz, again.xyz)
    np.testing.assert_array_equal(first.rgb, again.rgb)
    np.testing.assert_array_equal(first.chunk_spacing, again.chunk_spacing)
    np.save(kept[0], np.arange(10, dtype=np.uint32))  # another scan's order: recomputed, not trusted
    third = prepare_cloud(load_scan(tmp_path / "room.ply"), chunk=1024)
    np.testing.assert_array_equal(first.xyz, third.xyz)
    assert "another scan" in caplog.text
    assert np.load(kept[0]).shape == (len(scan),)  # and rewritten
    from services.io.decimate import random_decimate

    half = random_decimate(load_scan(tmp_path / "room.ply"), 0.5)  # a decimated scan keeps no order in the file's cache
    prepare_cloud(half, chunk=1024)
    assert "cache_dir" not in half.meta and np.load(kept[0]).shape == (len(scan),)


def test_morton_codes_interleave_the_grid_cells_bits():
    from services.render.cloud import _morton_codes

    rng = np.random.default_rng(5)
    xyz = rng.normal(0, 20, (20000, 3)).astype(np.float32)
    lo = xyz.min(axis=0)
    q = np.floor((xyz - lo) / np.float32(0.05)).astype(np.int64)
    want = np.zeros(len(xyz), np.uint64)
    for bit in range(21):  # bit b of axis a lands on bit 3 b + a
        for a in range(3):
            want |= ((q[:, a].astype(np.uint64) >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + a)
    np.testing.assert_array_equal(_morton_codes(xyz, lo, np.float32(0.05)), want)


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_motion_blur_on_the_torch_device_matches_the_numpy_blur(device):
    """The GPU server blurs renders with grid_sample; it must be the same blur as the OpenCV path: a distorted
    camera, depth with holes (far away), a grey and a colour image, and a wild pose that must stay finite."""
    import cv2

    from services.geometry.blur import motion_blur_linear
    from services.render.blur_torch import motion_blur_linear_torch

    rng = np.random.default_rng(3)
    cam = Camera(200, 150, 150.0, 150.0, 99.5, 74.5, (-0.2, 0.05, 0.001, -0.001, 0.0))
    grey = cv2.GaussianBlur(rng.integers(0, 255, (150, 200), dtype=np.uint8), (0, 0), 2)
    colour = cv2.GaussianBlur(rng.integers(0, 255, (150, 200, 3), dtype=np.uint8), (0, 0), 2)
    depth = np.linspace(1.5, 4.0, 200, dtype=np.float32)[None].repeat(150, 0)
    depth[60:80, 90:120] = 0.0  # no depth: far away on both paths
    T = Pose.from_rotvec_t([0.1, -0.2, 0.05], [1.0, 2.0, 1.5])
    a = T @ Pose.from_rotvec_t([0, -0.04, 0.01], [-0.02, 0, 0])  # ~12 px of blur
    b = T @ Pose.from_rotvec_t([0, 0.04, -0.01], [0.02, 0, 0])
    for img in (grey, colour):
        ref = motion_blur_linear(img, depth, cam, T, a, b, 9)
        got = motion_blur_linear_torch(img, depth, cam, T, a, b, 9, device)
        assert got.shape == ref.shape and got.dtype == np.float32
        assert np.abs(ref - img).mean() > 3  # a real blur ...
        inner = (slice(12, -12), slice(12, -12))  # (borders: OpenCV and torch reflect a half pixel apart)
        assert np.abs(ref - got)[inner].mean() < 0.05 and np.abs(ref - got)[inner].max() < 1.0
    assert np.array_equal(motion_blur_linear_torch(grey, depth, cam, T, a, b, 1, device), grey.astype(np.float32))
    wild = motion_blur_linear_torch(grey, depth, cam, T, T, T @ Pose.from_rotvec_t([0, 1.2, 0], [0, 0, 0.5]), 10, device)
    assert np.isfinite(wild).all()
