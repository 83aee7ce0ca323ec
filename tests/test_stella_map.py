"""The stella_vslam map format: writer, reader (ours, stella-saved, old OpenVSLAM keys), and the validator's every rule."""

import copy
import subprocess
import sys

import msgpack
import numpy as np
import pytest
import yaml

from services.features.orb import desc_to_u32, u32_to_desc
from services.geometry.camera import Camera
from services.geometry.se3 import Pose, look_at
from services.prebuild.stella_map import (DEFAULT_ORB_NAME, MapCamera, MapKeyframe, OrbParams, StellaMap, check_map_dict,
                                          check_map_dir, config_yaml, map_to_dict, read_map, write_config, write_map)

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5, (-0.1, 0.02, 0.001, -0.001, 0.0))


def small_map(n_kf: int = 3, n_lm: int = 12, seed: int = 0) -> StellaMap:
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-1, 3, -0.5], [1, 4, 0.5], (n_lm, 3))
    kfs = {}
    for k in range(n_kf):
        T_wc = look_at([0.2 * k, 0, 0], [0.2 * k, 1, 0], (0, 0, 1))
        Xc = T_wc.inverse().transform(pts)
        uv = np.stack([CAM.fx * Xc[:, 0] / Xc[:, 2] + CAM.cx, CAM.fy * Xc[:, 1] / Xc[:, 2] + CAM.cy], 1)
        kfs[k] = MapKeyframe(k, T_wc, uv.astype(np.float32), rng.uniform(0, 360, n_lm).astype(np.float32),
                             rng.integers(0, 8, n_lm).astype(np.int32), rng.integers(0, 256, (n_lm, 32), dtype=np.uint8),
                             np.arange(n_lm, dtype=np.int64), "cam", DEFAULT_ORB_NAME, float(k),
                             span_parent=k - 1, span_children=[k + 1] if k + 1 < n_kf else [])
    return StellaMap({"cam": MapCamera.from_camera("cam", CAM)}, {DEFAULT_ORB_NAME: OrbParams()}, kfs,
                     np.arange(n_lm, dtype=np.int64), pts, np.zeros(n_lm, np.int64), np.zeros(n_lm, np.int64),
                     np.full(n_lm, 3, np.int64), np.full(n_lm, 2, np.int64), n_kf, n_lm, n_kf)


def test_descriptor_words_are_little_endian_uint32():
    d = np.arange(32, dtype=np.uint8)[None]
    w = desc_to_u32(d)
    assert w[0, 0] == 0x03020100 and w.shape == (1, 8)
    assert np.array_equal(u32_to_desc(w.astype(np.int64).tolist()), d)


def test_round_trip_and_plain_types(tmp_path):
    m = small_map()
    size = write_map(m, tmp_path / "map.msg")
    assert size == (tmp_path / "map.msg").stat().st_size
    raw = msgpack.unpackb((tmp_path / "map.msg").read_bytes(), raw=False)
    assert check_map_dict(raw) == []
    back = read_map(tmp_path)  # the folder works as well as the file
    assert back.n_keyframes == 3 and back.n_landmarks == 12
    for k, kf in m.keyframes.items():
        b = back.keyframes[k]
        assert np.allclose(b.T_wc.matrix(), kf.T_wc.matrix(), atol=1e-12)
        assert np.allclose(b.kpts, kf.kpts) and np.array_equal(b.desc, kf.desc)
        assert np.array_equal(b.octaves, kf.octaves) and np.array_equal(b.lm_ids, kf.lm_ids)
        assert b.span_parent == kf.span_parent and b.span_children == kf.span_children
    assert np.allclose(back.lm_pos, m.lm_pos) and np.array_equal(back.lm_ref_kf, m.lm_ref_kf)
    assert back.cameras["cam"].camera() == CAM
    # world-to-camera in the file: the landmarks project where the keypoints are
    e = raw["keyframes"]["1"]
    R_cw = Pose.from_quat_t(e["rot_cw"], e["trans_cw"])
    Xc = R_cw.transform(m.lm_pos)
    u = CAM.fx * Xc[:, 0] / Xc[:, 2] + CAM.cx
    assert np.allclose(u, [k["pt"][0] for k in e["undist_keypts"]], atol=1e-3)


def test_reads_old_openvslam_keys(tmp_path):
    m = small_map()
    d = map_to_dict(m, legacy_keys=True)
    kf = d["keyframes"]["0"]
    assert {"keypts", "undists", "src_frm_id", "depth_thr", "n_scale_levels", "scale_factor"} <= set(kf)
    # distorted keypoints undistort back to the stored undistorted ones
    dist = np.array([k["pt"] for k in kf["keypts"]])
    und = CAM.undistort_points(dist) * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]
    assert np.allclose(und, kf["undists"], atol=1e-4)
    assert check_map_dict(d) == []
    # an OpenVSLAM 0.2 file: no undist_keypts, no orb_params table (ORB settings per keyframe)
    old = copy.deepcopy(d)
    for e in old["keyframes"].values():
        del e["undist_keypts"]
    old["orb_params"] = {}
    (tmp_path / "old.msg").write_bytes(msgpack.packb(old, use_bin_type=True))
    back = read_map(tmp_path / "old.msg")
    assert np.allclose(back.keyframes[2].kpts, m.keyframes[2].kpts, atol=1e-4)
    assert back.orb_params[DEFAULT_ORB_NAME].num_levels == 8


def test_reads_a_stella_saved_map_with_extra_keys(tmp_path):
    d = map_to_dict(small_map())
    for e in d["keyframes"].values():  # stella writes more than it reads back; the reader ignores the rest
        e["bow_vec"] = {}
        e["n_scale_levels"] = 8
    d["cameras"]["cam"]["extra"] = 1
    (tmp_path / "s.msg").write_bytes(msgpack.packb(d, use_bin_type=True))
    assert read_map(tmp_path / "s.msg").n_landmarks == 12


def _break(rule_fn):
    d = map_to_dict(small_map())
    rule_fn(d)
    return check_map_dict(d)


def _set(d, path, value):
    o = d
    for k in path[:-1]:
        o = o[k]
    o[path[-1]] = value


BREAKS = {
    "R0 bytes value": ("R0", lambda d: _set(d, ["keyframes", "0", "cam"], b"cam")),
    "R0 missing top key": ("R0", lambda d: d.pop("landmark_next_id")),
    "R0 missing keyframe key": ("R0", lambda d: d["keyframes"]["1"].pop("loop_edges")),
    "R0 missing landmark key": ("R0", lambda d: d["landmarks"]["3"].pop("pos_w")),
    "R0 integer map key": ("R0", lambda d: d["cameras"].update({7: d["cameras"]["cam"]})),
    "R1 unobserved landmark": ("R1", lambda d: [e["lm_ids"].__setitem__(5, -1) for e in d["keyframes"].values()]),
    "R1 ref_keyfrm does not observe": ("R1", lambda d: d["keyframes"]["0"]["lm_ids"].__setitem__(4, -1)),
    "R1 lm_ids names no landmark": ("R1", lambda d: d["keyframes"]["2"]["lm_ids"].__setitem__(0, 999)),
    "R1 landmark twice in a keyframe": ("R1", lambda d: d["keyframes"]["2"]["lm_ids"].__setitem__(1, 0)),
    "R2 octave >= num_levels": ("R2", lambda d: d["keyframes"]["1"]["undist_keypts"][3].__setitem__("oct", 8)),
    "R2 negative octave": ("R2", lambda d: d["keyframes"]["1"]["undist_keypts"][3].__setitem__("oct", -1)),
    "R3 descs shorter": ("R3", lambda d: d["keyframes"]["1"]["descs"].pop()),
    "R3 lm_ids shorter": ("R3", lambda d: d["keyframes"]["1"]["lm_ids"].pop()),
    "R3 n_keypts wrong": ("R3", lambda d: _set(d, ["keyframes", "1", "n_keypts"], 13)),
    "R3 depths shorter": ("R3", lambda d: d["keyframes"]["1"]["depths"].pop()),
    "R4 non-unit quaternion": ("R4", lambda d: _set(d, ["keyframes", "1", "rot_cw"], [0.0, 0.0, 0.0, 1.01])),
    "R4 id not decimal": ("R4", lambda d: d["landmarks"].update({"07": d["landmarks"].pop("7")})),
    "R4 keyframe_next_id too small": ("R4", lambda d: _set(d, ["keyframe_next_id"], 2)),
    "R4 landmark_next_id too small": ("R4", lambda d: _set(d, ["landmark_next_id"], 11)),
    "R5 two roots": ("R5", lambda d: (_set(d, ["keyframes", "2", "span_parent"], -1), d["keyframes"]["1"].__setitem__("span_children", []))),
    "R5 parent does not list child": ("R5", lambda d: _set(d, ["keyframes", "0", "span_children"], [])),
    "R5 child with another parent": ("R5", lambda d: _set(d, ["keyframes", "0", "span_children"], [1, 2])),
    "R5 unknown parent": ("R5", lambda d: _set(d, ["keyframes", "2", "span_parent"], 9)),
    "R6 seven words": ("R6", lambda d: d["keyframes"]["0"]["descs"][0].pop()),
    "R6 word beyond uint32": ("R6", lambda d: d["keyframes"]["0"]["descs"][0].__setitem__(0, 1 << 32)),
    "R7 n_fnd > n_vis": ("R7", lambda d: _set(d, ["landmarks", "2", "n_fnd"], 9)),
    "R7 unknown camera": ("R7", lambda d: _set(d, ["keyframes", "1", "cam"], "other")),
    "R7 unknown ORB set": ("R7", lambda d: _set(d, ["keyframes", "1", "orb_params"], "other")),
    "R7 non-finite position": ("R7", lambda d: _set(d, ["landmarks", "2", "pos_w"], [0.0, float("nan"), 1.0])),
}


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_validator_catches_every_broken_rule(name):
    rule, fn = BREAKS[name]
    problems = check_map_dict(_break_copy(fn))
    assert problems, f"{name}: validator accepted a broken map"
    assert rule in {p.rule for p in problems}, f"{name}: expected {rule}, got {problems}"


def _break_copy(fn):
    d = map_to_dict(small_map())
    fn(d)
    return d


def test_cycle_in_spanning_tree_is_caught():
    d = map_to_dict(small_map())
    # 0 -> 1 -> 2 -> 1: keyframe 1's parent becomes 2 (and 2 lists it); 0 still the only root
    d["keyframes"]["1"]["span_parent"] = 2
    d["keyframes"]["2"]["span_children"] = [1]
    d["keyframes"]["0"]["span_children"] = []
    assert "R5" in {p.rule for p in check_map_dict(d)}


def test_config_yaml_agrees_with_map_and_mismatch_fails(tmp_path):
    m = small_map()
    write_map(m, tmp_path / "map.msg")
    write_config(tmp_path / "config.yaml", m.cameras["cam"], m.orb_params[DEFAULT_ORB_NAME])
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["Camera"]["name"] == "cam" and cfg["Camera"]["setup"] == "monocular"
    assert cfg["Feature"]["scale_factor"] == 1.2 and cfg["Feature"]["num_levels"] == 8
    assert cfg["Feature"]["ini_fast_threshold"] == 20 and cfg["Feature"]["min_fast_threshold"] == 7
    problems, stats = check_map_dir(tmp_path)
    assert problems == [] and stats["config"]
    bad = config_yaml(m.cameras["cam"], OrbParams(scale_factor=1.3))
    (tmp_path / "config.yaml").write_text(bad)
    assert "R7" in {p.rule for p in check_map_dir(tmp_path)[0]}


def test_map_check_command_exit_codes(tmp_path):
    m = small_map()
    write_map(m, tmp_path / "good" / "map.msg")
    # the installed entry point (under 'python -m services.cli' CliError would be another class than the handler's)
    run = lambda p: subprocess.run([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main(sys.argv[1:]))",
                                    "map", "check", str(p)], capture_output=True, text=True)
    ok = run(tmp_path / "good")
    assert ok.returncode == 0, ok.stdout + ok.stderr
    d = map_to_dict(m)
    d["keyframes"]["1"]["undist_keypts"][0]["oct"] = 9
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "map.msg").write_bytes(msgpack.packb(d, use_bin_type=True))
    bad = run(tmp_path / "bad")
    assert bad.returncode == 1 and "R2" in bad.stdout and "FAIL" in bad.stdout
    missing = run(tmp_path / "nothing")
    assert missing.returncode == 2
