"""A site filmed after it changed (``cristal sim --changes``): the scan as built, the camera's day with furniture and
stock moved, taken away or added."""

import json

import numpy as np
import pytest

from services.io.sequence import open_sequence
from services.sim.changes import _route_distance, change_scene
from services.sim.scenes import make_scene
from services.sim.site import SimSite, config_for, generate_site


def _object_boxes(mesh):
    """Per object id: the (min, max) corners of its vertices."""
    obj = mesh.object_ids()
    out = {}
    for k in np.unique(obj[obj >= 0]):
        v = mesh.vertices[np.unique(mesh.faces[obj == k])]
        out[int(k)] = (v.min(0), v.max(0))
    return out


def test_a_changed_warehouse_moves_removes_and_adds_about_the_share_asked_and_keeps_the_building():
    scene = make_scene("warehouse", 3)
    mesh, summary = change_scene(scene, 0.3, np.random.default_rng(0))
    assert summary["movable"] > 1000
    changed = summary["moved"] + summary["removed"]
    assert 0.25 * summary["movable"] < changed < 0.35 * summary["movable"]
    assert summary["added"] == pytest.approx(changed / 3, abs=1)
    # the building (walls, floor, racks' frames) is untouched, face for face
    old = scene.mesh.object_ids() < 0
    new = mesh.object_ids() < 0
    assert np.array_equal(scene.mesh.vertices[scene.mesh.faces[old]], mesh.vertices[mesh.faces[new]])
    # objects: some gone, some elsewhere, new ones on the floor away from the route
    before, after = _object_boxes(scene.mesh), _object_boxes(mesh)
    assert len(before) - summary["removed"] + summary["added"] == len(after)
    moved = [k for k in before if k in after and not np.allclose(before[k][0], after[k][0])]
    assert len(moved) == summary["moved"]
    for k in range(max(before) + 1, max(after) + 1):
        lo, hi = after[k]
        assert lo[2] == pytest.approx(0.0) and 0.3 <= hi[2] <= 1.0
        centre = 0.5 * (lo[:2] + hi[:2])
        assert _route_distance(centre[None], scene.route)[0] > 0.6
    # deterministic, and nothing changed at 0
    again, _ = change_scene(scene, 0.3, np.random.default_rng(0))
    assert np.array_equal(again.vertices, mesh.vertices) and np.array_equal(again.faces, mesh.faces)
    same, s0 = change_scene(scene, 0.0, np.random.default_rng(0))
    assert s0["moved"] == s0["removed"] == s0["added"] == 0 and np.array_equal(same.vertices, scene.mesh.vertices)
    with pytest.raises(ValueError, match="within 0..1"):
        change_scene(scene, 1.5, np.random.default_rng(0))


def test_a_site_filmed_after_changes_has_the_same_scan_and_walk_and_other_pictures(small_site, tmp_path):
    """The scan and the ground truth are the unchanged site's to the byte; frames differ where the site changed."""
    out, cfg, _ = small_site
    changed_cfg = config_for("office", seed=3, frames=12, width=200, height=150, lidar_step_deg=0.6,
                             distortion=(-0.1, 0.02, 0.0, 0.0, 0.0), changes=0.5)
    summary = generate_site(changed_cfg, tmp_path)
    assert (tmp_path / "scan.ply").read_bytes() == (out / "scan.ply").read_bytes()
    for f in ("groundtruth.txt", "rgb.txt", "camera.json"):
        assert (tmp_path / "seq_00" / f).read_bytes() == (out / "seq_00" / f).read_bytes()
    c = summary["changes"]
    assert c["moved"] + c["removed"] > 0 and c["added"] >= 1
    assert json.loads((tmp_path / "site.json").read_text())["changes"] == c
    assert (tmp_path / "mesh_camera.npz").exists() and not (out / "mesh_camera.npz").exists()
    # the camera-day mesh differs from the scanned one in some frame's view (depth from the same pose)
    site = SimSite(tmp_path)
    seq = open_sequence(tmp_path / "seq_00")
    diff = 0.0
    for i in range(0, 12, 3):
        _, d_scan = site.render(seq.groundtruth.poses[i], seq.camera, "scan")
        _, d_cam = site.render(seq.groundtruth.poses[i], seq.camera, "camera")
        diff = max(diff, float((np.abs(d_scan - d_cam) > 0.05).mean()))
    assert diff > 0.005, "no frame of the walk sees what changed"
    # and generating the same folder again without changes leaves no camera-day mesh behind
    generate_site(cfg, tmp_path)
    assert not (tmp_path / "mesh_camera.npz").exists()


def test_what_rests_on_an_object_goes_where_it_goes():
    """A desk taken away takes its monitor; a desk moved carries it: the monitor turns and shifts exactly as the desk
    does (unless it was moved on its own as well), and is never left where it stood."""
    scene = make_scene("office", 1)
    mesh0 = scene.mesh
    parents = mesh0.object_parents()
    pairs = [(int(p), c) for c, p in enumerate(parents) if p >= 0]
    assert len(pairs) >= 3  # two monitors, a box on a cabinet, a box on a table
    obj0 = mesh0.object_ids()

    def vertex_ids(k):  # (change_scene keeps the scene's vertex array in order: the same ids after)
        return np.unique(mesh0.faces[obj0 == k])

    seen_gone = seen_carried = False
    for seed in range(12):
        mesh, _ = change_scene(scene, 0.5, np.random.default_rng(seed))
        present = set(np.unique(mesh.object_ids()).tolist())
        for p, c in pairs:
            vp, vc = vertex_ids(p), vertex_ids(c)
            if p not in present:
                assert c not in present, f"seed {seed}: object {c} floats where {p} was"
                seen_gone = True
                continue
            a, b = mesh0.vertices[vp], mesh.vertices[vp]
            if np.allclose(a, b) or c not in present:
                continue
            assert not np.allclose(mesh0.vertices[vc], mesh.vertices[vc]), f"seed {seed}: {c} stayed when {p} moved"
            # the parent's turn and shift (a rigid motion in the floor plane), applied to the child
            ca, cb = a[:, :2].mean(0), b[:, :2].mean(0)
            u, _, vt = np.linalg.svd((a[:, :2] - ca).T @ (b[:, :2] - cb))
            R = (u @ vt).T
            carried = (mesh0.vertices[vc][:, :2] - ca) @ R.T + cb
            seen_carried |= bool(np.allclose(carried, mesh.vertices[vc][:, :2], atol=1e-9))
    assert seen_gone and seen_carried
