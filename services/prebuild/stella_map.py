"""The OpenVSLAM / stella_vslam map database (MessagePack): dataclasses, writer, reader, validator.

The format and every loader rule are in the shared docs (``STELLA_MAP_FORMAT.md``). In short: one
MessagePack map with string keys and only str/int/float/bool/list/dict values (stella parses it
with nlohmann/json, which rejects ``bin``/``ext``); poses stored world-to-camera (``rot_cw`` as
``[qx, qy, qz, qw]``, ``trans_cw``); keypoints undistorted; descriptors as 8 uint32; landmark
observations only through the keyframes' ``lm_ids``.

Our world is the scan frame, so ``T_cw`` here is simply ``T_wc.inverse()`` of a keyframe's
camera-to-world pose; the conversion happens in this module and nowhere else.

Light: numpy, msgpack and PyYAML only (the on-device localizer loads maps with it).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

from services.features.orb import desc_to_u32, u32_to_desc
from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.io.atomic import atomic_write_bytes, atomic_write_text

__all__ = ["MapCamera", "OrbParams", "MapKeyframe", "StellaMap", "MapError", "Violation",
           "write_map", "read_map", "map_to_dict", "map_from_dict", "check_map_dict", "check_map_dir",
           "config_yaml", "DEFAULT_ORB_NAME", "MAP_FILE", "CONFIG_FILE"]

log = logging.getLogger(__name__)

DEFAULT_ORB_NAME = "default ORB feature extraction setting"
MAP_FILE = "map.msg"
CONFIG_FILE = "config.yaml"


class MapError(ValueError):
    """A map file that cannot be read or breaks a loader rule; the message says which."""


# ---------------------------------------------------------------------------------------------- model
@dataclass(frozen=True)
class MapCamera:
    name: str
    cols: int
    rows: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    fps: float = 30.0
    color_order: str = "RGB"

    @classmethod
    def from_camera(cls, name: str, cam: Camera, fps: float = 30.0, color_order: str = "RGB") -> "MapCamera":
        k1, k2, p1, p2, k3 = cam.distortion
        return cls(name, int(cam.width), int(cam.height), float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy),
                   k1, k2, p1, p2, k3, float(fps), color_order)

    def camera(self) -> Camera:
        return Camera(int(self.cols), int(self.rows), self.fx, self.fy, self.cx, self.cy,
                      (self.k1, self.k2, self.p1, self.p2, self.k3))

    def entry(self) -> dict:
        return {"model_type": "Perspective", "setup_type": "Monocular", "color_order": self.color_order,
                "cols": int(self.cols), "rows": int(self.rows), "fps": float(self.fps), "focal_x_baseline": 0.0,
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "k1": float(self.k1), "k2": float(self.k2), "p1": float(self.p1), "p2": float(self.p2), "k3": float(self.k3)}

    @classmethod
    def from_entry(cls, name: str, e: dict) -> "MapCamera":
        return cls(name, int(e["cols"]), int(e["rows"]), float(e["fx"]), float(e["fy"]), float(e["cx"]), float(e["cy"]),
                   float(e.get("k1", 0)), float(e.get("k2", 0)), float(e.get("p1", 0)), float(e.get("p2", 0)),
                   float(e.get("k3", 0)), float(e.get("fps", 30.0)), str(e.get("color_order", "RGB")))


@dataclass(frozen=True)
class OrbParams:
    name: str = DEFAULT_ORB_NAME
    scale_factor: float = 1.2
    num_levels: int = 8
    ini_fast_threshold: int = 20
    min_fast_threshold: int = 7

    def entry(self) -> dict:
        return {"name": self.name, "scale_factor": float(self.scale_factor), "num_levels": int(self.num_levels),
                "ini_fast_threshold": int(self.ini_fast_threshold), "min_fast_threshold": int(self.min_fast_threshold)}

    @classmethod
    def from_entry(cls, name: str, e: dict) -> "OrbParams":
        return cls(str(e.get("name", name)), float(e["scale_factor"]), int(e["num_levels"]),
                   int(e["ini_fast_threshold"]), int(e["min_fast_threshold"]))


@dataclass
class MapKeyframe:
    id: int
    T_wc: Pose  # camera-to-world in the scan frame (the file stores its inverse)
    kpts: np.ndarray  # (N, 2) float32 undistorted pixels
    angles: np.ndarray  # (N,) float32 degrees
    octaves: np.ndarray  # (N,) int32
    desc: np.ndarray  # (N, 32) uint8
    lm_ids: np.ndarray  # (N,) int64, -1 where the keypoint has no landmark
    cam: str = "camera"
    orb_params: str = DEFAULT_ORB_NAME
    ts: float = 0.0
    span_parent: int = -1
    span_children: list[int] = field(default_factory=list)
    loop_edges: list[int] = field(default_factory=list)

    def __len__(self) -> int:
        return int(len(self.kpts))


@dataclass
class StellaMap:
    cameras: dict[str, MapCamera]
    orb_params: dict[str, OrbParams]
    keyframes: dict[int, MapKeyframe]
    lm_ids: np.ndarray  # (M,) int64
    lm_pos: np.ndarray  # (M, 3) float64 world
    lm_first_kf: np.ndarray  # (M,) int64
    lm_ref_kf: np.ndarray  # (M,) int64
    lm_n_vis: np.ndarray  # (M,) int64
    lm_n_fnd: np.ndarray  # (M,) int64
    keyframe_next_id: int = 0
    landmark_next_id: int = 0
    frame_next_id: int = 0

    @property
    def n_keyframes(self) -> int:
        return len(self.keyframes)

    @property
    def n_landmarks(self) -> int:
        return int(len(self.lm_ids))

    def camera(self, name: str | None = None) -> Camera:
        return self.cameras[name or next(iter(self.cameras))].camera()


# ---------------------------------------------------------------------------------------------- write
def _pose_cw(T_wc: Pose) -> tuple[list[float], list[float]]:
    T_cw = T_wc.inverse()
    return [float(v) for v in T_cw.quat_xyzw()], [float(v) for v in T_cw.t]


def map_to_dict(m: StellaMap, legacy_keys: bool = False) -> dict:
    """The MessagePack-ready dict (plain Python types only).

    ``legacy_keys`` also writes what OpenVSLAM <= 0.2.x read (``keypts`` distorted, ``undists``,
    ``src_frm_id``, ``depth_thr``, ``n_scale_levels``, ``scale_factor``).
    """
    kfs = {}
    for kid, kf in m.keyframes.items():
        n = len(kf)
        q, t = _pose_cw(kf.T_wc)
        pts = kf.kpts.astype(np.float64).tolist()
        angs = kf.angles.astype(np.float64).tolist()
        octs = kf.octaves.astype(np.int64).tolist()
        e = {
            "ts": float(kf.ts), "cam": kf.cam, "orb_params": kf.orb_params,
            "rot_cw": q, "trans_cw": t, "n_keypts": n,
            "undist_keypts": [{"pt": p, "ang": a, "oct": o} for p, a, o in zip(pts, angs, octs)],
            "x_rights": [-1.0] * n, "depths": [-1.0] * n,
            "descs": desc_to_u32(kf.desc).astype(np.int64).tolist(),
            "lm_ids": kf.lm_ids.astype(np.int64).tolist(),
            "span_parent": int(kf.span_parent), "span_children": [int(c) for c in kf.span_children],
            "loop_edges": [int(c) for c in kf.loop_edges],
        }
        if legacy_keys:
            cam = m.cameras[kf.cam].camera()
            if cam.is_distorted:
                xn = (kf.kpts[:, 0].astype(np.float64) - cam.cx) / cam.fx
                yn = (kf.kpts[:, 1].astype(np.float64) - cam.cy) / cam.fy
                dpts, _ = cam.project(np.stack([xn, yn, np.ones_like(xn)], 1))
                dpts = dpts.tolist()
            else:
                dpts = pts
            op = m.orb_params[kf.orb_params]
            e.update({"keypts": [{"pt": p, "ang": a, "oct": o} for p, a, o in zip(dpts, angs, octs)],
                      "undists": pts, "src_frm_id": int(kid), "depth_thr": 0.0,
                      "n_scale_levels": int(op.num_levels), "scale_factor": float(op.scale_factor)})
        kfs[str(int(kid))] = e
    lms = {}
    for i in range(m.n_landmarks):
        lms[str(int(m.lm_ids[i]))] = {
            "1st_keyfrm": int(m.lm_first_kf[i]), "pos_w": [float(v) for v in m.lm_pos[i]],
            "ref_keyfrm": int(m.lm_ref_kf[i]), "n_vis": int(m.lm_n_vis[i]), "n_fnd": int(m.lm_n_fnd[i])}
    return {
        "cameras": {name: c.entry() for name, c in m.cameras.items()},
        "orb_params": {name: o.entry() for name, o in m.orb_params.items()},
        "keyframes": kfs,
        "landmarks": lms,
        "keyframe_next_id": int(m.keyframe_next_id),
        "landmark_next_id": int(m.landmark_next_id),
        "frame_next_id": int(m.frame_next_id),
    }


def write_map(m: StellaMap, path: str | Path, legacy_keys: bool = False) -> int:
    """Write ``map.msg`` atomically; returns its size in bytes."""
    data = msgpack.packb(map_to_dict(m, legacy_keys), use_bin_type=True)
    atomic_write_bytes(path, data)
    return len(data)


def config_yaml(cam: MapCamera, orb: OrbParams, max_num_keypoints: int = 2000) -> str:
    """The stella_vslam config that matches a map: camera block (same name) and Feature block (same ORB set).

    Keys for both current stella_vslam (``Preprocessing``) and older releases (``Feature.max_num_keypoints``).
    """
    def num(v: float) -> str:
        return repr(float(v))

    return f"""\
# stella_vslam config written by cristal prebuild: localize with
#   run_image_slam -v orb_vocab.fbow -c config.yaml --map-db-in map.msg --disable-mapping
# The camera and Feature blocks must stay as they are: the map's keyframes and ORB parameters refer to them.

Camera:
  name: "{cam.name}"
  setup: "monocular"
  model: "perspective"
  fx: {num(cam.fx)}
  fy: {num(cam.fy)}
  cx: {num(cam.cx)}
  cy: {num(cam.cy)}
  k1: {num(cam.k1)}
  k2: {num(cam.k2)}
  p1: {num(cam.p1)}
  p2: {num(cam.p2)}
  k3: {num(cam.k3)}
  fps: {num(cam.fps)}
  cols: {int(cam.cols)}
  rows: {int(cam.rows)}
  color_order: "{cam.color_order}"

Preprocessing:
  min_size: 800
  max_num_keypoints: {int(max_num_keypoints)}

Feature:
  name: "{orb.name}"
  scale_factor: {num(orb.scale_factor)}
  num_levels: {int(orb.num_levels)}
  ini_fast_threshold: {int(orb.ini_fast_threshold)}
  min_fast_threshold: {int(orb.min_fast_threshold)}
  max_num_keypoints: {int(max_num_keypoints)}

System:
  map_format: "msgpack"
"""


def write_config(path: str | Path, cam: MapCamera, orb: OrbParams, max_num_keypoints: int = 2000) -> None:
    atomic_write_text(path, config_yaml(cam, orb, max_num_keypoints))


# ---------------------------------------------------------------------------------------------- read
def _load_dict(path: str | Path) -> dict:
    path = Path(path)
    if path.is_dir():
        path = path / MAP_FILE
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise MapError(f"{path}: no such map file") from None
    try:
        d = msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as e:  # msgpack raises several unrelated types
        raise MapError(f"{path}: not a MessagePack map ({e})") from None
    if not isinstance(d, dict):
        raise MapError(f"{path}: top level is {type(d).__name__}, expected a map")
    return d


def _keyframe_from_entry(kid: int, e: dict) -> MapKeyframe:
    n = int(e["n_keypts"])
    if "undist_keypts" in e:
        kp = e["undist_keypts"]
        pts = np.array([k["pt"] for k in kp], dtype=np.float32).reshape(-1, 2)
        ang = np.array([k["ang"] for k in kp], dtype=np.float32)
        octs = np.array([k["oct"] for k in kp], dtype=np.int32)
    else:  # OpenVSLAM <= 0.2.x: bare undistorted points, angles/octaves in the distorted keypoints
        pts = np.array(e["undists"], dtype=np.float32).reshape(-1, 2)
        kp = e["keypts"]
        ang = np.array([k["ang"] for k in kp], dtype=np.float32)
        octs = np.array([k["oct"] for k in kp], dtype=np.int32)
    desc = u32_to_desc(e["descs"]) if len(e["descs"]) else np.zeros((0, 32), np.uint8)
    lm = np.array(e["lm_ids"], dtype=np.int64)[:n]
    T_cw = Pose.from_quat_t(e["rot_cw"], e["trans_cw"])
    return MapKeyframe(kid, T_cw.inverse(), pts, ang, octs, desc, lm, str(e["cam"]), str(e.get("orb_params", DEFAULT_ORB_NAME)),
                       float(e.get("ts", 0.0)), int(e.get("span_parent", -1)),
                       [int(c) for c in e.get("span_children", [])], [int(c) for c in e.get("loop_edges", [])])


def map_from_dict(d: dict) -> StellaMap:
    try:
        cams = {str(k): MapCamera.from_entry(str(k), v) for k, v in d["cameras"].items()}
        orbs = {str(k): OrbParams.from_entry(str(k), v) for k, v in d.get("orb_params", {}).items()}
        kfs = {int(k): _keyframe_from_entry(int(k), v) for k, v in d["keyframes"].items()}
        for kf in kfs.values():  # maps from OpenVSLAM <= 0.2.x: ORB settings per keyframe, no orb_params table
            if kf.orb_params not in orbs:
                e = d["keyframes"][str(kf.id)]
                if "scale_factor" in e and "n_scale_levels" in e:
                    orbs[kf.orb_params] = OrbParams(kf.orb_params, float(e["scale_factor"]), int(e["n_scale_levels"]))
        ids = sorted(int(k) for k in d["landmarks"])
        L = d["landmarks"]
        ent = [L[str(i)] for i in ids]
        m = StellaMap(
            cams, orbs, kfs,
            np.array(ids, dtype=np.int64),
            np.array([e["pos_w"] for e in ent], dtype=np.float64).reshape(-1, 3),
            np.array([e["1st_keyfrm"] for e in ent], dtype=np.int64),
            np.array([e["ref_keyfrm"] for e in ent], dtype=np.int64),
            np.array([e.get("n_vis", 1) for e in ent], dtype=np.int64),
            np.array([e.get("n_fnd", 1) for e in ent], dtype=np.int64),
            int(d.get("keyframe_next_id", max(kfs, default=-1) + 1)),
            int(d.get("landmark_next_id", (ids[-1] + 1) if ids else 0)),
            int(d.get("frame_next_id", 0)),
        )
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, MapError):
            raise
        raise MapError(f"map is missing or has a malformed field: {e!r}") from None
    return m


def read_map(path: str | Path) -> StellaMap:
    """Read a map written by us or by stella_vslam / OpenVSLAM (``map.msg`` or the folder holding it)."""
    return map_from_dict(_load_dict(path))


# ---------------------------------------------------------------------------------------------- validate
@dataclass(frozen=True)
class Violation:
    rule: str  # e.g. "R1"
    message: str

    def __str__(self) -> str:
        return f"[{self.rule}] {self.message}"


RULES = {
    "R0": "encoding: a MessagePack map, string keys, only str/int/float/bool/list/dict (no bin/ext), every required key",
    "R1": "every landmark is observed by at least one keyframe, and by its own ref_keyfrm; lm_ids name existing landmarks",
    "R2": "keypoint octaves are in [0, num_levels) of their ORB parameter set",
    "R3": "len(undist_keypts) == len(descs) == n_keypts and len(lm_ids) >= n_keypts (also x_rights, depths)",
    "R4": "unit quaternions, ids as decimal strings, *_next_id beyond the largest id",
    "R5": "spanning tree: one root with parent -1, every other keyframe's parent lists it as a child, all reach the root",
    "R6": "descriptors are 8 uint32 words each",
    "R7": "references: keyframe cameras and ORB sets exist; 1 <= n_fnd <= n_vis; finite positions; config.yaml agrees",
}

_TOP = ("cameras", "orb_params", "keyframes", "landmarks", "keyframe_next_id", "landmark_next_id", "frame_next_id")
_CAM = ("model_type", "setup_type", "color_order", "cols", "rows", "fps", "focal_x_baseline", "fx", "fy", "cx", "cy",
        "k1", "k2", "p1", "p2", "k3")
_ORB = ("name", "scale_factor", "num_levels", "ini_fast_threshold", "min_fast_threshold")
_KF = ("ts", "cam", "orb_params", "rot_cw", "trans_cw", "n_keypts", "undist_keypts", "x_rights", "depths", "descs",
       "lm_ids", "span_parent", "span_children", "loop_edges")
_LM = ("1st_keyfrm", "pos_w", "ref_keyfrm", "n_vis", "n_fnd")


def _plain_types(obj, path: str, out: list[Violation], limit: int = 5) -> None:
    """R0: only str/int/float/bool/None/list/dict with string keys, anywhere."""
    stack = [(obj, path)]
    while stack and len(out) < limit:
        o, p = stack.pop()
        if isinstance(o, dict):
            for k, v in o.items():
                if not isinstance(k, str):
                    out.append(Violation("R0", f"{p}: map key {k!r} is a {type(k).__name__}, must be a string"))
                if isinstance(v, (dict, list)):
                    stack.append((v, f"{p}/{k}"))
                elif not isinstance(v, (str, int, float, bool)) and v is not None:
                    out.append(Violation("R0", f"{p}/{k}: {type(v).__name__} value (MessagePack bin/ext is rejected by stella_vslam)"))
        elif isinstance(o, list):
            for i, v in enumerate(o):
                if isinstance(v, (dict, list)):
                    stack.append((v, f"{p}[{i}]"))
                elif not isinstance(v, (str, int, float, bool)) and v is not None:
                    out.append(Violation("R0", f"{p}[{i}]: {type(v).__name__} value (MessagePack bin/ext is rejected by stella_vslam)"))


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _dec_id(k) -> int | None:
    if isinstance(k, str) and k.isdigit() and str(int(k)) == k:
        return int(k)
    return None


def check_map_dict(d, config: dict | None = None, max_per_rule: int = 5) -> list[Violation]:
    """Every loader rule of STELLA_MAP_FORMAT.md; an empty list means stella_vslam can load the map.

    ``config``: the parsed ``config.yaml`` shipped next to the map (checked against the map's camera and ORB set).
    """
    out: list[Violation] = []
    counts: dict[str, int] = {}

    def bad(rule: str, msg: str) -> None:
        counts[rule] = counts.get(rule, 0) + 1
        if counts[rule] <= max_per_rule:
            out.append(Violation(rule, msg))
        elif counts[rule] == max_per_rule + 1:
            out.append(Violation(rule, "... more violations of this rule not listed"))

    if not isinstance(d, dict):
        return [Violation("R0", f"top level is a {type(d).__name__}, must be a map")]
    enc: list[Violation] = []
    _plain_types(d, "", enc)
    for v in enc:
        bad(v.rule, v.message)
    for k in _TOP:
        if k not in d:
            bad("R0", f"top-level key '{k}' is missing")
    cams = d.get("cameras") if isinstance(d.get("cameras"), dict) else {}
    orbs = d.get("orb_params") if isinstance(d.get("orb_params"), dict) else {}
    kfs = d.get("keyframes") if isinstance(d.get("keyframes"), dict) else {}
    lms = d.get("landmarks") if isinstance(d.get("landmarks"), dict) else {}
    for name, c in cams.items():
        if not isinstance(c, dict):
            bad("R0", f"camera '{name}' is not a map")
            continue
        for k in _CAM:
            if k not in c:
                bad("R0", f"camera '{name}': key '{k}' is missing")
        if c.get("model_type") != "Perspective":
            bad("R7", f"camera '{name}': model_type {c.get('model_type')!r}, this writer/validator handles 'Perspective'")
        if c.get("setup_type") != "Monocular":
            bad("R7", f"camera '{name}': setup_type {c.get('setup_type')!r}, expected 'Monocular'")
        if c.get("color_order") not in ("Gray", "RGB", "BGR"):
            bad("R7", f"camera '{name}': color_order {c.get('color_order')!r} is not Gray, RGB or BGR")
        for k in ("fx", "fy", "cx", "cy", "cols", "rows"):
            if k in c and not _is_num(c[k]):
                bad("R7", f"camera '{name}': {k} is not a finite number")
    for name, o in orbs.items():
        if not isinstance(o, dict):
            bad("R0", f"orb_params '{name}' is not a map")
            continue
        for k in _ORB:
            if k not in o:
                bad("R0", f"orb_params '{name}': key '{k}' is missing")
        if "num_levels" in o and (not _is_int(o["num_levels"]) or o["num_levels"] < 1):
            bad("R7", f"orb_params '{name}': num_levels {o['num_levels']!r} is not a positive integer")
    # ---- R4 ids
    def by_id(kind: str, entries: dict) -> dict[int, dict]:
        out: dict[int, dict] = {}
        for k, e in entries.items():
            i = _dec_id(k)
            if i is None:
                bad("R4", f"{kind} id {k!r} is not a decimal string")
            elif not isinstance(e, dict):
                bad("R0", f"{kind} {k} is not a map")
            else:
                out[i] = e
        return out

    kf_ids, lm_ids = by_id("keyframe", kfs), by_id("landmark", lms)
    for key, ids in (("keyframe_next_id", kf_ids), ("landmark_next_id", lm_ids)):
        v = d.get(key)
        if key in d and (not _is_int(v) or (ids and v <= max(ids))):
            bad("R4", f"{key} = {v!r} must be an integer greater than every id (largest {max(ids) if ids else None})")
    if "frame_next_id" in d and not _is_int(d["frame_next_id"]):
        bad("R4", f"frame_next_id = {d['frame_next_id']!r} must be an integer")
    # ---- keyframes
    observers: dict[int, set[int]] = {}
    for kid, e in kf_ids.items():
        missing = [k for k in _KF if k not in e]
        if missing:
            bad("R0", f"keyframe {kid}: keys {missing} are missing")
            continue
        if e["cam"] not in cams and not (config and e["cam"] == config.get("Camera", {}).get("name")):
            bad("R7", f"keyframe {kid}: camera {e['cam']!r} is not in 'cameras' (nor the config)")
        orb = orbs.get(e["orb_params"])
        if orb is None:
            bad("R7", f"keyframe {kid}: ORB parameter set {e['orb_params']!r} is not in 'orb_params'")
        q = e["rot_cw"]
        if not (isinstance(q, list) and len(q) == 4 and all(_is_num(x) for x in q)):
            bad("R4", f"keyframe {kid}: rot_cw must be 4 numbers [qx, qy, qz, qw]")
        elif abs(math.sqrt(sum(x * x for x in q)) - 1.0) > 1e-6:
            bad("R4", f"keyframe {kid}: rot_cw has norm {math.sqrt(sum(x * x for x in q)):.9f}, must be a unit quaternion")
        t = e["trans_cw"]
        if not (isinstance(t, list) and len(t) == 3 and all(_is_num(x) for x in t)):
            bad("R7", f"keyframe {kid}: trans_cw must be 3 finite numbers")
        n = e["n_keypts"]
        if not _is_int(n) or n < 0:
            bad("R3", f"keyframe {kid}: n_keypts {n!r} is not a non-negative integer")
            continue
        kps, descs, lm = e["undist_keypts"], e["descs"], e["lm_ids"]
        for key, arr in (("undist_keypts", kps), ("descs", descs), ("x_rights", e["x_rights"]), ("depths", e["depths"])):
            if not isinstance(arr, list) or len(arr) != n:
                bad("R3", f"keyframe {kid}: len({key}) = {len(arr) if isinstance(arr, list) else None} != n_keypts = {n}")
        if not isinstance(lm, list) or len(lm) < n:
            bad("R3", f"keyframe {kid}: len(lm_ids) = {len(lm) if isinstance(lm, list) else None} < n_keypts = {n}")
            lm = []
        if isinstance(kps, list):
            nl = orb["num_levels"] if isinstance(orb, dict) and _is_int(orb.get("num_levels")) else None
            for j, kp in enumerate(kps):
                if not (isinstance(kp, dict) and "pt" in kp and "ang" in kp and "oct" in kp):
                    bad("R0", f"keyframe {kid}: keypoint {j} must be {{pt, ang, oct}}")
                    break
                o = kp["oct"]
                if not _is_int(o) or o < 0 or (nl is not None and o >= nl):
                    bad("R2", f"keyframe {kid}: keypoint {j} octave {o!r} outside [0, {nl})")
                    break
                p = kp["pt"]
                if not (isinstance(p, list) and len(p) == 2 and all(_is_num(x) for x in p)) or not _is_num(kp["ang"]):
                    bad("R0", f"keyframe {kid}: keypoint {j} has a malformed pt/ang")
                    break
        if isinstance(descs, list):
            for j, ds in enumerate(descs):
                if not (isinstance(ds, list) and len(ds) == 8 and all(_is_int(w) and 0 <= w <= 0xFFFFFFFF for w in ds)):
                    bad("R6", f"keyframe {kid}: descriptor {j} is not 8 uint32 words")
                    break
        seen: set[int] = set()
        for j, li in enumerate(lm[:n]):
            if not _is_int(li):
                bad("R1", f"keyframe {kid}: lm_ids[{j}] = {li!r} is not an integer")
                continue
            if li < 0:
                continue
            if li not in lm_ids:
                bad("R1", f"keyframe {kid}: lm_ids[{j}] = {li} names no landmark")
                continue
            if li in seen:
                bad("R1", f"keyframe {kid}: landmark {li} is observed by two keypoints of the same keyframe")
            seen.add(li)
            observers.setdefault(li, set()).add(kid)
    # ---- R5 spanning tree
    roots = [k for k, e in kf_ids.items() if e.get("span_parent") == -1]
    if kf_ids and len(roots) != 1:
        bad("R5", f"{len(roots)} keyframes have span_parent -1 (roots {sorted(roots)[:5]}), need exactly one")
    for kid, e in kf_ids.items():
        p = e.get("span_parent")
        ch = e.get("span_children", [])
        if not _is_int(p):
            bad("R5", f"keyframe {kid}: span_parent {p!r} is not an integer")
            continue
        if p != -1:
            pe = kf_ids.get(p)
            if pe is None:
                bad("R5", f"keyframe {kid}: span_parent {p} is not a keyframe")
            elif kid not in (pe.get("span_children") or []):
                bad("R5", f"keyframe {kid}: parent {p} does not list it in span_children")
        if not isinstance(ch, list):
            bad("R5", f"keyframe {kid}: span_children is not a list")
            continue
        for c in ch:
            ce = kf_ids.get(c) if _is_int(c) else None
            if ce is None:
                bad("R5", f"keyframe {kid}: span child {c!r} is not a keyframe")
            elif ce.get("span_parent") != kid:
                bad("R5", f"keyframe {kid}: lists child {c} whose span_parent is {ce.get('span_parent')}")
        for c in e.get("loop_edges", []) or []:
            if c not in kf_ids:
                bad("R7", f"keyframe {kid}: loop edge {c!r} is not a keyframe")
    if len(roots) == 1:  # all reach the root through parents (no cycles)
        reached = {roots[0]}
        for kid in kf_ids:
            path, k = [], kid
            while k not in reached and k in kf_ids and len(path) <= len(kf_ids):
                path.append(k)
                k = kf_ids[k].get("span_parent")
            if k in reached:
                reached.update(path)
            else:
                bad("R5", f"keyframe {kid}: following span_parent never reaches the root {roots[0]} (cycle or broken link)")
                break
    # ---- landmarks
    for lid, e in lm_ids.items():
        missing = [k for k in _LM if k not in e]
        if missing:
            bad("R0", f"landmark {lid}: keys {missing} are missing")
            continue
        obs = observers.get(lid, set())
        if not obs:
            bad("R1", f"landmark {lid} is observed by no keyframe")
        elif e["ref_keyfrm"] not in obs:
            bad("R1", f"landmark {lid}: ref_keyfrm {e['ref_keyfrm']!r} does not observe it (observed by {sorted(obs)[:5]})")
        if e["1st_keyfrm"] not in kf_ids:
            bad("R7", f"landmark {lid}: 1st_keyfrm {e['1st_keyfrm']!r} is not a keyframe")
        p = e["pos_w"]
        if not (isinstance(p, list) and len(p) == 3 and all(_is_num(x) for x in p)):
            bad("R7", f"landmark {lid}: pos_w must be 3 finite numbers")
        nv, nf = e["n_vis"], e["n_fnd"]
        if not (_is_int(nv) and _is_int(nf) and 1 <= nf <= nv):
            bad("R7", f"landmark {lid}: need 1 <= n_fnd <= n_vis, got n_fnd={nf!r}, n_vis={nv!r}")
    # ---- config.yaml next to the map
    if config is not None:
        cc = config.get("Camera") or {}
        name = cc.get("name")
        if name not in cams:
            bad("R7", f"config.yaml Camera.name {name!r} is not a camera of the map ({sorted(cams)})")
        else:
            c = cams[name]
            for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "cols", "rows"):
                if k in cc and _is_num(c.get(k)) and abs(float(cc[k]) - float(c[k])) > 1e-6 * max(1.0, abs(float(c[k]))):
                    bad("R7", f"config.yaml Camera.{k} = {cc[k]} but the map's camera has {c[k]}")
        f = config.get("Feature") or {}
        fname = f.get("name", DEFAULT_ORB_NAME)
        o = orbs.get(fname)
        if o is None:
            bad("R7", f"config.yaml Feature.name {fname!r} is not an ORB set of the map ({sorted(orbs)})")
        else:
            for k in ("scale_factor", "num_levels", "ini_fast_threshold", "min_fast_threshold"):
                if k in f and abs(float(f[k]) - float(o.get(k, float("nan")))) > 1e-6:
                    bad("R7", f"config.yaml Feature.{k} = {f[k]} but orb_params '{fname}' has {o.get(k)}")
    return out


def check_map_dir(map_dir: str | Path) -> tuple[list[Violation], dict]:
    """Validate ``MAPDIR/map.msg`` (and ``MAPDIR/config.yaml`` when present). Returns (violations, stats)."""
    import yaml

    map_dir = Path(map_dir)
    path = map_dir / MAP_FILE if map_dir.is_dir() else map_dir
    try:
        d = _load_dict(path)
    except MapError as e:
        return [Violation("R0", str(e))], {}
    cfg_path = path.parent / CONFIG_FILE
    config = None
    if cfg_path.exists():
        try:
            config = yaml.safe_load(cfg_path.read_text())
        except yaml.YAMLError as e:
            return [Violation("R7", f"{cfg_path}: not valid YAML ({e})")], {}
    stats = {"keyframes": len(d.get("keyframes", {}) or {}), "landmarks": len(d.get("landmarks", {}) or {}),
             "bytes": path.stat().st_size, "config": cfg_path.exists()}
    return check_map_dict(d, config), stats
