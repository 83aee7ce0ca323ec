"""``cristal sim`` (generate a simulated site) and ``cristal sim-view`` (ground-truth render of one)."""

from __future__ import annotations

import argparse

# services.sim.lidar.FLAWS's names (importing it here would load numba for every cristal command; test_sim checks them)
FLAW_NAMES = ("none", "survey", "registration", "poor", "loose")

SIM_EPILOG = """\
examples:
  cristal sim --preset office --seed 1 --out site/            the default: ~4 M points, one 300-frame 640x480 walk
  cristal sim --preset office --frames 60 --lidar-step 0.4 --out small/   a quick small site (tests, demos)
  cristal sim --preset warehouse --seed 3 --out wh/            60 x 40 m hall with shelf rows, 600 frames
  cristal sim --preset office --distortion -0.12 0.03 0 0 0 --out lens/   a camera with radial distortion
  cristal sim --preset office --rolling-shutter 20 --out rs/     a phone-like rolling shutter (rows read over 20 ms)
  cristal sim --preset office --scan-flaws survey --out real/    a scan as registration software leaves it
  cristal sim --preset office --scan-colour intensity --out nir/  a scanner that took no pictures (intensity only)
  cristal sim --preset office --changes 0.3 --out later/       filmed weeks after the scan: 30 % of the furniture
                                                               moved or gone, new boxes about

what you get (docs/CONVENTIONS.md layout):
  site/scan.ply                    colored LiDAR scan, world frame in metres (z up)
  site/seq_00/rgb/*.jpg rgb.txt    the camera sequence (JPEG, motion blur, noise, other lighting than the scan)
  site/seq_00/camera.json          intrinsics
  site/seq_00/groundtruth.txt      TUM camera-to-world poses
  site/mesh.npz, site/site.json    the mesh and settings, for ground-truth renders (cristal sim-view)
  site/mesh_camera.npz             with --changes: the mesh the camera filmed (site.json says what changed)
"""

VIEW_EPILOG = """\
example:
  cristal sim-view site/ --pose "3 2.5 1.5 -0.5 0.5 -0.5 0.5" --camera site/seq_00/camera.json --out gt.png --depth gt_depth.npy

The pose is camera-to-world 'tx ty tz qx qy qz qw' (OpenCV camera axes: x right, y down, z forward).
--lighting scan (default) shows the site as the scanner saw it: the target a point renderer should reproduce.
"""


def register(sub) -> None:
    p = sub.add_parser("sim", help="generate a simulated site: LiDAR scan + camera sequences with ground truth",
                       description="Generate a simulated site (deterministic from preset and seed).",
                       epilog=SIM_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="office", choices=["office", "warehouse"], help="scene (default: office)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default: 1)")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--frames", type=int, help="frames per sequence (office 300, warehouse 600)")
    p.add_argument("--sequences", type=int, help="number of camera sequences (default 1)")
    p.add_argument("--fps", type=float, help="frame rate (default 30)")
    p.add_argument("--width", type=int, help="image width (default 640)")
    p.add_argument("--height", type=int, help="image height (default 480)")
    p.add_argument("--hfov", type=float, dest="hfov_deg", help="horizontal field of view in degrees (default 66)")
    p.add_argument("--distortion", type=float, nargs=5, metavar=("K1", "K2", "P1", "P2", "K3"),
                   help="OpenCV lens distortion of the camera (default: none)")
    p.add_argument("--rolling-shutter", type=float, metavar="MS",
                   help="rolling-shutter readout time in ms, rows top to bottom (phones: 10-30; default 0 = global "
                        "shutter); stamps and ground truth are the middle row's")
    p.add_argument("--lidar-step", type=float, dest="lidar_step_deg",
                   help="scanner angular step in degrees (office 0.2, warehouse 0.4); halving it quadruples the points")
    p.add_argument("--scan-colour", choices=["rgb", "intensity"], default="rgb",
                   help="rgb: the scanner's camera coloured every point (default); intensity: it took no pictures, "
                        "each point has the laser's return strength instead (a near-infrared reflectance that follows "
                        "the visible colours only loosely), as many E57 and LAS exports")
    p.add_argument("--scan-flaws", choices=FLAW_NAMES, default="none",
                   help="what a real registered scan gets wrong: each station registered a little off, its panorama "
                        "exposed and white-balanced apart, mixed pixels floating along silhouettes. survey: 3 mm / "
                        "0.01 deg, 10 %% exposure, 30 %% of edge returns mixed; registration: the survey's registration "
                        "alone; poor: 1 cm / 0.03 deg, 30 %%, all; loose: 1 mm / 0.003 deg but one station (the one "
                        "nearest the stations' middle) 1 cm / 0.03 deg off (default: none, a perfect scan)")
    p.add_argument("--changes", type=float, default=0.0, metavar="FRACTION",
                   help="the site changed after the scan: this share (0-1) of its movable objects (desks, chairs, "
                        "shelf boxes, pallets with their load) moved or taken away, and new boxes on the floor, a "
                        "third as many as those changed. The scan shows the site as built, the camera the changed one "
                        "(default 0: as scanned)")
    p.set_defaults(func=run_sim)

    v = sub.add_parser("sim-view", help="ground-truth render (RGB + depth) of a simulated site from any pose",
                       description="Ray-trace the simulated site's mesh from a pose.", epilog=VIEW_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    v.add_argument("site", help="folder written by 'cristal sim'")
    v.add_argument("--pose", required=True, help="camera-to-world 'tx ty tz qx qy qz qw'")
    v.add_argument("--camera", required=True, help="camera.json")
    v.add_argument("--out", required=True, help="output PNG")
    v.add_argument("--depth", help="also write the z-depth (metres, float32) as .npy")
    v.add_argument("--lighting", choices=["scan", "camera"], default="scan",
                   help="scan: the colours the scanner recorded (what the renderer should reproduce; default); camera: the light the walk's camera saw")
    v.set_defaults(func=run_view)


def run_sim(args) -> int:
    import time

    from services.cli import CliError, emit_summary
    from services.sim.site import config_for, generate_site

    if args.rolling_shutter is not None and not 0 <= args.rolling_shutter <= 200:
        raise CliError(f"--rolling-shutter is the readout in milliseconds, 0 to 200 (got {args.rolling_shutter:g})")
    if not 0 <= args.changes <= 1:
        raise CliError(f"--changes is the share of movable objects changed, 0 to 1 (got {args.changes:g})")

    cfg = config_for(args.preset, seed=args.seed, frames=args.frames, sequences=args.sequences, fps=args.fps,
                     width=args.width, height=args.height, hfov_deg=args.hfov_deg,
                     distortion=tuple(args.distortion) if args.distortion else None, lidar_step_deg=args.lidar_step_deg,
                     readout_s=args.rolling_shutter / 1000.0 if args.rolling_shutter else None,
                     scan_flaws=None if args.scan_flaws == "none" else args.scan_flaws,
                     scan_intensity=args.scan_colour == "intensity", changes=args.changes)
    t0 = time.perf_counter()
    s = generate_site(cfg, args.out)
    dt = time.perf_counter() - t0
    print(f"site {args.out}: preset {s['preset']} seed {s['seed']}, {s['points']:,} points from "
          f"{len(s['stations'])} stations, sequences: {', '.join(q['name'] + ' (' + str(q['frames']) + ' frames)' for q in s['sequences'])}; "
          f"{dt:.1f} s")
    if s.get("changes"):
        c = s["changes"]
        print(f"changed after the scan: {c['moved']} of {c['movable']} movable objects moved, {c['removed']} taken away, "
              f"{c['added']} new boxes")
    emit_summary({"out": str(args.out), "preset": s["preset"], "seed": s["seed"], "points": s["points"],
                  "sequences": [q["name"] for q in s["sequences"]], "seconds": round(dt, 2), **s["timings"]})
    return 0


def run_view(args) -> int:
    import cv2
    import numpy as np

    from services.cli import emit_summary, parse_pose
    from services.geometry.camera import Camera
    from services.io.atomic import atomic_write, atomic_write_bytes
    from services.sim.site import SimSite

    T_wc = parse_pose(args.pose)
    cam = Camera.load(args.camera)
    site = SimSite(args.site)
    rgb, depth = site.render(T_wc, cam, args.lighting)
    ok, buf = cv2.imencode(".png", rgb[..., ::-1])
    atomic_write_bytes(args.out, buf.tobytes())
    if args.depth:
        with atomic_write(args.depth, "wb") as f:
            np.save(f, depth)
    emit_summary({"out": args.out, "hit_fraction": float((depth > 0).mean()), "depth_max": float(depth.max())})
    return 0
