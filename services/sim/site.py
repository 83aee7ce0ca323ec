"""Generate a simulated site folder (scan + camera sequences with ground truth), and render ground truth later.

Layout written (``docs/CONVENTIONS.md``)::

    <out>/scan.ply                 the simulated LiDAR scan (world frame, metres)
    <out>/site.json                preset, seed, settings, stations, lighting, exposure, timings, counts
    <out>/mesh.npz                 the textured mesh: ground-truth renders for any pose (``SimSite.render``)
    <out>/mesh_camera.npz          only with ``changes``: the mesh the camera filmed (moved furniture, new boxes)
    <out>/<sequence>/rgb/*.jpg, rgb.txt, camera.json, groundtruth.txt

Everything is deterministic from (preset, seed, settings).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from services.geometry.blur import motion_blur
from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.io.atomic import atomic_write_text
from services.io.scan import Scan
from services.io.sequence import SequenceWriter
from services.log import progress
from services.sim.lidar import FLAWS, LidarConfig, ScanFlaws, loose_station, misregister, scan_exposure, simulate_station
from services.sim.materials import linear_to_srgb
from services.sim.mesh import Mesh
from services.sim.scenes import Lighting, Scene, make_scene
from services.sim.sensor import AutoExposure, SensorModel, blur_samples, develop
from services.sim.shading import SceneRenderer
from services.sim.walk import make_walk

__all__ = ["SiteConfig", "PRESET_DEFAULTS", "generate_site", "SimSite", "SITE_FORMAT_VERSION"]

log = logging.getLogger(__name__)
SITE_FORMAT_VERSION = 1


@dataclass(frozen=True)
class SiteConfig:
    preset: str = "office"
    seed: int = 1
    lidar: LidarConfig = field(default_factory=LidarConfig)
    flaws: ScanFlaws = field(default_factory=ScanFlaws)  # what a real registered scan gets wrong (none by default)
    sequences: int = 1
    frames: int = 300
    fps: float = 30.0
    width: int = 640
    height: int = 480
    hfov_deg: float = 66.0
    distortion: tuple[float, float, float, float, float] | None = None  # None: an undistorted camera
    sensor: SensorModel = field(default_factory=SensorModel)
    walk_speed: float = 0.9
    changes: float = 0.0  # share of movable objects changed between the scan and the camera's day (sim.changes)
    start_time: float = 1700000000.0


PRESET_DEFAULTS = {
    "office": SiteConfig(preset="office"),
    "warehouse": SiteConfig(preset="warehouse", lidar=LidarConfig(step_deg=0.4), frames=600, walk_speed=1.2),
}


def _camera(cfg: SiteConfig) -> Camera:
    return Camera.from_fov(cfg.width, cfg.height, cfg.hfov_deg, cfg.distortion or (0, 0, 0, 0, 0))


def generate_site(cfg: SiteConfig, out: str | Path) -> dict:
    """Simulate the scan and the camera sequences into ``out``; returns a summary (also in site.json)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    scene = make_scene(cfg.preset, cfg.seed)
    renderer = SceneRenderer(scene.mesh, texture_seed=cfg.seed)
    scene.mesh.save(out / "mesh.npz")
    camera_renderer, changes = renderer, None  # what the camera films: the scene as scanned, or changed since
    if cfg.changes > 0:
        from services.sim.changes import change_scene

        changed, changes = change_scene(scene, cfg.changes, np.random.default_rng([cfg.seed, 7]))
        changed.save(out / "mesh_camera.npz")
        camera_renderer = SceneRenderer(changed, texture_seed=cfg.seed)
        log.info("changed after the scan: %d of %d movable objects moved, %d taken away, %d new boxes",
                 changes["moved"], changes["movable"], changes["removed"], changes["added"])
    elif (out / "mesh_camera.npz").exists():
        (out / "mesh_camera.npz").unlink()  # (a site regenerated into the same folder without changes)
    timings["scene_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    exposure = scan_exposure(renderer, scene.stations, scene.scan_lighting, cfg.seed)
    rng = np.random.default_rng([cfg.seed, 1])
    xyz_parts, rgb_parts, stations = [], [], []  # (rgb_parts: intensities for a scanner that took no pictures)
    intensity_seed = cfg.seed if cfg.lidar.intensity_only else None
    loose = loose_station(scene.stations) if (cfg.flaws.loose_m or cfg.flaws.loose_deg) else -1
    for k, c in enumerate(progress(scene.stations, desc="LiDAR stations", total=len(scene.stations), unit="station")):
        frng = np.random.default_rng([cfg.seed, 3, k]) if cfg.flaws.any else None  # (a perfect scan draws as before)
        xyz, rgb = simulate_station(renderer, c, scene.scan_lighting, exposure, cfg.lidar, rng,
                                    cfg.flaws if cfg.flaws.any else None, frng, intensity_seed)
        R, centre = np.eye(3), c
        if cfg.flaws.misregistered:
            xyz, R, centre = misregister(xyz, c, cfg.flaws, frng, loose=k == loose)
        xyz_parts.append(xyz)
        rgb_parts.append(rgb)
        stations.append(Pose(R, centre))  # where the registration put the station
    world = np.concatenate(xyz_parts)
    intensity = np.concatenate(rgb_parts) if cfg.lidar.intensity_only else None
    rgb = np.zeros((len(world), 3), np.uint8) if cfg.lidar.intensity_only else np.concatenate(rgb_parts)
    scan = Scan(world.astype(np.float32), rgb, np.zeros(3), stations,
                meta={"station_points": [len(x) for x in xyz_parts]})
    del world
    from services.io.scans import save_ply

    save_ply(scan, out / "scan.ply", intensity=intensity)
    timings["scan_s"] = time.perf_counter() - t0
    log.info("scan: %d points from %d stations -> %s", len(scan), len(stations), out / "scan.ply")

    camera = _camera(cfg)
    seqs = []
    for k in range(cfg.sequences):
        t0 = time.perf_counter()
        name = f"seq_{k:02d}"
        n = _write_sequence(scene, renderer, camera_renderer, cfg, camera, out / name,
                            np.random.default_rng([cfg.seed, 100 + k]))
        timings[f"{name}_s"] = time.perf_counter() - t0
        seqs.append({"name": name, "frames": n})
        log.info("sequence %s: %d frames -> %s", name, n, out / name)

    summary = {
        "format_version": SITE_FORMAT_VERSION,
        "preset": cfg.preset,
        "seed": cfg.seed,
        "config": _jsonable(asdict(cfg)),
        "points": len(scan),
        "faces": scene.mesh.n_faces,
        "stations": scene.stations.tolist(),
        "scan_lighting": scene.scan_lighting.to_dict(),
        "camera_lighting": scene.camera_lighting.to_dict(),
        "scan_exposure": exposure,
        "bounds": [list(scene.bounds[0]), list(scene.bounds[1])],
        "sequences": seqs,
        "changes": changes,
        "timings": {k: round(v, 2) for k, v in timings.items()},
    }
    atomic_write_text(out / "site.json", json.dumps(summary, indent=2) + "\n")
    return summary


def _write_sequence(scene: Scene, scanned: SceneRenderer, renderer: SceneRenderer, cfg: SiteConfig, camera: Camera,
                    root: Path, rng: np.random.Generator) -> int:
    """The walk is planned on the site as ``scanned`` (the same walk with and without changes since the scan) and
    filmed by ``renderer``."""
    duration = cfg.frames / cfg.fps
    walk = make_walk(scene, scanned, duration, rng, speed=cfg.walk_speed)
    ae = AutoExposure(cfg.sensor)
    exp = cfg.sensor.exposure_time_s
    with SequenceWriter(root, camera, ".jpg", cfg.sensor.jpeg_quality) as w:
        for i in progress(range(cfg.frames), desc=f"frames {root.name}", total=cfg.frames, unit="frame"):
            t = i / cfg.fps
            T_wc = walk.pose(t)
            if cfg.sensor.readout_s > 0:  # rolling shutter: row v is read at t + ((v + 0.5) / H - 0.5) * readout
                H, ro = camera.height, cfg.sensor.readout_s
                rows = [walk.pose(t + ((v + 0.5) / H - 0.5) * ro) for v in range(H)]
                rad, depth = renderer.render_rows(rows, camera, scene.camera_lighting)
            else:
                rad, depth = renderer.render(T_wc, camera, scene.camera_lighting)
            Ta, Tb = walk.pose(t - exp / 2), walk.pose(t + exp / 2)
            n_sub = blur_samples(camera, Ta, Tb, cfg.sensor.max_blur_samples)
            if n_sub > 1:
                subs = [walk.pose(t - exp / 2 + (j + 0.5) / n_sub * exp) for j in range(n_sub)]
                rad = motion_blur(rad, depth, camera, T_wc, subs)
            gain = ae.update(rad)
            rgb = develop(rad, gain, cfg.sensor, rng)
            w.add(f"{cfg.start_time + t:.6f}", rgb[..., ::-1], T_wc)
    return cfg.frames


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


class SimSite:
    """A generated site, reopened: ground-truth renders of the mesh for any pose and camera.

    ``render(T_wc, camera)`` returns what the point cloud *should* look like from there (scan-day
    lighting and the scanner's exposure, same colour pipeline as the scan's points): the target
    for training and scoring the point renderer. ``lighting="camera"`` gives the camera-day look (and, with
    ``--changes``, the camera-day site).
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)
        meta_path = self.root / "site.json"
        if not meta_path.exists():
            raise FileNotFoundError(f"{meta_path}: not a simulated site folder (run 'cristal sim' first)")
        self.meta = json.loads(meta_path.read_text())
        if self.meta.get("format_version") != SITE_FORMAT_VERSION:
            raise ValueError(f"{meta_path}: site format {self.meta.get('format_version')} is not {SITE_FORMAT_VERSION}")
        self.mesh = Mesh.load(self.root / "mesh.npz")
        self.renderer = SceneRenderer(self.mesh, texture_seed=int(self.meta["seed"]))
        self.camera_renderer = self.renderer  # the site the camera filmed: changed since the scan, or the same
        if (self.root / "mesh_camera.npz").exists():
            self.camera_renderer = SceneRenderer(Mesh.load(self.root / "mesh_camera.npz"), texture_seed=int(self.meta["seed"]))
        self.scan_lighting = Lighting.from_dict(self.meta["scan_lighting"])
        self.camera_lighting = Lighting.from_dict(self.meta["camera_lighting"])
        self.exposure = float(self.meta["scan_exposure"])

    def render(self, T_wc: Pose, camera: Camera, lighting: str = "scan") -> tuple[np.ndarray, np.ndarray]:
        """(H,W,3) uint8 RGB and (H,W) float32 z-depth in metres (0 where nothing is hit)."""
        light = {"scan": self.scan_lighting, "camera": self.camera_lighting}[lighting]
        renderer = self.renderer if lighting == "scan" else self.camera_renderer
        rad, depth = renderer.render(T_wc, camera, light)
        gain = self.exposure if lighting == "scan" else 0.16 / max(float(rad.mean()), 1e-6)
        rgb = (linear_to_srgb(rad * gain) * 255.0 + 0.5).astype(np.uint8)
        return rgb, depth


def config_for(preset: str, **overrides) -> SiteConfig:
    """The preset's defaults with some fields replaced (``lidar_step_deg`` reaches into the LiDAR settings)."""
    if preset not in PRESET_DEFAULTS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESET_DEFAULTS)}")
    base = PRESET_DEFAULTS[preset]
    step = overrides.pop("lidar_step_deg", None)
    if step is not None:
        base = replace(base, lidar=replace(base.lidar, step_deg=float(step)))
    flaws = overrides.pop("scan_flaws", None)
    if flaws is not None:
        if flaws not in FLAWS:
            raise ValueError(f"unknown scan flaws {flaws!r}; choose from {', '.join(FLAWS)}")
        base = replace(base, flaws=FLAWS[flaws])
    if overrides.pop("scan_intensity", False):
        base = replace(base, lidar=replace(base.lidar, intensity_only=True))
    readout = overrides.pop("readout_s", None)
    if readout is not None:
        base = replace(base, sensor=replace(base.sensor, readout_s=float(readout)))
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return replace(base, **overrides)
