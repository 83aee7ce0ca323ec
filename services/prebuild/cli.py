"""``cristal prebuild`` (a stella_vslam map from the scan alone) and ``cristal map check`` (the loader rules)."""

from __future__ import annotations

import argparse

PREBUILD_EPILOG = """\
examples:
  cristal prebuild site/scan.ply --camera site/seq_00/camera.json --out site/map      region of interest from the scan
  cristal prebuild scan.e57 --camera cam.json --out map --spacing 0.75 --heights 1.3 1.7
  cristal prebuild scan.ply --camera cam.json --out map --stage splat                  ablation: no neural rendering
  cristal prebuild scan.ply --camera cam.json --out map --decimate 0.1                 from 10 %% of the points

Renders views with the camera's intrinsics at every position of a uniform grid in the region of
interest (all yaw directions, pitched up and down), extracts ORB with stella_vslam's settings,
back-projects keypoints with the render depth, merges landmarks seen by several keyframes and
writes MAPDIR/map.msg (stella_vslam / OpenVSLAM MessagePack map) and MAPDIR/config.yaml, atomically,
and MAPDIR/map.png: the keyframe positions over the landmarks, seen from above (where the map holds).
Localize with 'cristal localize MAPDIR SEQUENCE --method pnl --map MAPDIR', or with stella_vslam:
  run_image_slam -v orb_vocab.fbow -c MAPDIR/config.yaml --map-db-in MAPDIR/map.msg --disable-mapping
"""

CHECK_EPILOG = """\
examples:
  cristal map check site/map              MAPDIR with map.msg (and config.yaml)
  cristal map check some/other/map.msg    a map saved by stella_vslam itself

Checks every rule stella_vslam's loader relies on (docs: STELLA_MAP_FORMAT.md): encoding, required
keys, landmark observations and reference keyframes, octaves, array lengths, unit quaternions, ids,
the spanning tree, descriptor words, references, and config.yaml against the map. Exit code 1 and
one line per violation, naming the rule, when the map would not load.
"""


def register(sub) -> None:
    p = sub.add_parser("prebuild", help="build a stella_vslam map (ORB keyframes + landmarks) from the scan alone",
                       description="Prebuild & Localize: a drift-free stella_vslam map from renders of the scan.",
                       epilog=PREBUILD_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scan", help="scan file (.ply .e57 .las .laz)")
    p.add_argument("--camera", required=True, help="camera.json of the camera that will localize (intrinsics, distortion)")
    p.add_argument("--out", required=True, help="map folder (map.msg + config.yaml)")
    p.add_argument("--spacing", type=float, default=1.0, help="metres between positions (default 1.0)")
    p.add_argument("--heights", type=float, nargs="+", default=[1.5], help="camera heights above the floor (default 1.5)")
    p.add_argument("--margin", type=float, default=0.5, help="free space around each position in metres (default 0.5)")
    p.add_argument("--roi", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), help="box in world coordinates")
    p.add_argument("--roi-polygon", nargs="+", metavar="X,Y",
                   help="floor-plan outline in world x,y (>= 3 vertices); positions at --heights above the floor inside it")
    p.add_argument("--stage", choices=["full", "filter", "splat"], default="full",
                   help="renderer stage: full = neural (default), splat = plain point splats (ablation)")
    p.add_argument("--supersample", type=int, metavar="K",
                   help="render keyframes at K times their resolution and pool them (default 1): keypoints on edges "
                        "sit where the scan's samples put them. 2 on the simulated office: 0.35 -> 0.31 cm, a 30 %% "
                        "longer build; but 0.24 -> 0.44 cm on the tests' small site, whose renders have more holes "
                        "(66 %% of patches near one, the office 10 %%) and its corners land on colours the hole "
                        "filling drew (benchmarks/RESULTS.md, stop 40)")
    p.add_argument("--decimate", type=float, metavar="FRACTION", help="use a random fraction of the scan's points")
    p.add_argument("--max-keypoints", type=int, default=2000, help="ORB keypoints per rendered view (default 2000)")
    p.add_argument("--legacy-keys", action="store_true", help="also write the keys OpenVSLAM <= 0.2.x reads")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    p.set_defaults(func=run_prebuild)

    mp = sub.add_parser("map", help="stella_vslam map tools (check)", description="stella_vslam map tools.",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    msub = mp.add_subparsers(dest="map_command", metavar="ACTION")
    c = msub.add_parser("check", help="check a map against every stella_vslam loader rule", epilog=CHECK_EPILOG,
                        description="Validate a stella_vslam map.", formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("map", help="map folder (map.msg [+ config.yaml]) or a .msg file")
    c.set_defaults(func=run_check)


def run_prebuild(args) -> int:
    import os
    import time
    from pathlib import Path

    from services.cli import CliError, emit_summary, positions_picture, roi_polygon
    from services.geometry.camera import Camera
    from services.io.scans import load_scan
    from services.prebuild.builder import BuildConfig, build_map
    from services.localize.scan_error import describe, measure_scan, write_accuracy
    from services.prebuild.patches import PATCH_FILE
    from services.prebuild.stella_map import CONFIG_FILE, MAP_FILE, check_map_dict, map_to_dict, write_config, write_map
    from services.relocalize.roi import RoiConfig, sample_positions
    from services.render.renderer import Renderer

    t0 = time.perf_counter()
    cam = Camera.load(args.camera)
    if args.decimate is not None and not 0 < args.decimate <= 1:
        raise CliError(f"--decimate must be in (0, 1], got {args.decimate}")
    if getattr(args, "supersample", None) is not None and not 1 <= args.supersample <= 4:
        raise CliError(f"--supersample is a whole factor from 1 (off) to 4, got {args.supersample}")
    try:
        import torch

        torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    except ImportError:  # pragma: no cover
        pass
    scan = load_scan(args.scan)
    if args.decimate is not None and args.decimate < 1:
        from services.io.decimate import random_decimate

        scan = random_decimate(scan, args.decimate)
    pos = sample_positions(scan, RoiConfig(spacing=args.spacing, heights=tuple(args.heights), margin=args.margin,
                                           box=tuple(args.roi) if args.roi else None,
                                           polygon=roi_polygon(args.roi_polygon) if args.roi_polygon else None))
    if len(pos) == 0:
        raise CliError("no position in free space inside the region of interest: check --roi, --heights, --margin")
    renderer = Renderer(scan, device=args.device, holefill=args.stage == "full")
    base = BuildConfig()
    from dataclasses import replace

    cfg = replace(base, stage=args.stage, orb=replace(base.orb, max_keypoints=args.max_keypoints),
                  supersample=getattr(args, "supersample", None) or base.supersample)
    m, stats, patches = build_map(renderer, pos, cam, cfg, spacing=args.spacing)
    if m.n_landmarks == 0:
        raise CliError("the map has no landmark (no keypoint was seen by two keyframes): try a smaller --spacing")
    problems = check_map_dict(map_to_dict(m))
    if problems:  # our own writer broke a loader rule: a bug, never write such a map
        raise RuntimeError("built map breaks stella_vslam loader rules: " + "; ".join(map(str, problems[:5])))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    size = write_map(m, out / MAP_FILE, legacy_keys=args.legacy_keys)
    write_config(out / CONFIG_FILE, m.cameras[cfg.camera_name], next(iter(m.orb_params.values())), args.max_keypoints)
    if patches is not None:  # beside the map, for our light localizer; stella_vslam reads map.msg alone
        patches.save(out / PATCH_FILE)
    accuracy = measure_scan(scan)  # the scan's own error, for the light localizer's --scan-sigma-mm auto
    write_accuracy(out, accuracy)
    total = time.perf_counter() - t0
    print(f"map {out}: {m.n_keyframes} keyframes, {m.n_landmarks:,} landmarks, {size / 1e6:.1f} MB, "
          f"built in {stats['build_s']:.1f} s ({total:.1f} s with loading); stella_vslam config {out / CONFIG_FILE}; "
          f"{describe(accuracy)}")
    picture = positions_picture(pos, out / MAP_FILE, landmarks=m.lm_pos, label="keyframe positions",
                                title=f"map: {m.n_keyframes} keyframes at {len(pos)} positions, {m.n_landmarks:,} "
                                      f"landmarks (grey by height; top view)")
    emit_summary({"out": str(out), "bytes": size, "total_s": round(total, 2), "stage": args.stage,
                  "points": len(scan), "picture": picture and str(picture), "scan_sigma_mm": accuracy["scan_sigma_mm"],
                  **stats})
    return 0


def run_check(args) -> int:
    from pathlib import Path

    from services.cli import CliError, emit_summary
    from services.prebuild.stella_map import RULES, check_map_dir

    p = Path(args.map)
    if not p.exists():
        raise CliError(f"{p}: no such map folder or file")
    problems, stats = check_map_dir(p)
    for v in problems:
        print(f"FAIL {v}  ({RULES.get(v.rule, '')})")
    if not problems:
        print(f"OK {p}: {stats.get('keyframes')} keyframes, {stats.get('landmarks')} landmarks, "
              f"{stats.get('bytes', 0) / 1e6:.1f} MB; every stella_vslam loader rule holds"
              + ("" if stats.get("config") else " (no config.yaml beside it: not checked)"))
    patch_error = _check_patches(p) if p.is_dir() else None
    if patch_error:
        print(f"FAIL {patch_error}")
    emit_summary({"map": str(p), "ok": not problems and not patch_error, "violations": len(problems),
                  "rules": sorted({v.rule for v in problems}), "patches_error": patch_error, **stats})
    return 1 if problems or patch_error else 0


def _check_patches(map_dir) -> str | None:
    """The landmark patches beside a map (our light localizer's sidecar): loadable and about this map's landmarks."""
    import numpy as np

    from services.prebuild.patches import PATCH_FILE, LandmarkPatches, map_fingerprint
    from services.prebuild.stella_map import read_map

    f = map_dir / PATCH_FILE
    if not f.is_file():
        return None
    try:
        lp = LandmarkPatches.load(f)
    except ValueError as e:
        return str(e)
    m = read_map(map_dir)
    if lp.map_fp != map_fingerprint(m.lm_ids, m.lm_pos):
        return f"{f}: made for another map (fingerprint {lp.map_fp or 'none'}): rebuild the map, or delete it"
    unknown = np.setdiff1d(lp.lm_ids, m.lm_ids)
    if len(unknown):
        return f"{f}: {len(unknown)} patches for landmarks the map does not have"
    print(f"OK {f}: {len(lp.lm_ids):,} landmark patches of {lp.size}x{lp.size} px")
    return None
