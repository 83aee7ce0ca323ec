"""``cristal build-db`` (relocalization database) and ``cristal localize`` (poses for a sequence)."""

from __future__ import annotations

import argparse
import json
import logging

log = logging.getLogger(__name__)

DB_EPILOG = """\
examples:
  cristal build-db site/scan.ply --out site/reloc.npz                      region of interest derived from the scan
  cristal build-db scan.e57 --out db.npz --spacing 2 --heights 1.2 1.7     coarser grid, two camera heights
  cristal build-db scan.ply --out db.npz --roi 0 0 0.5 12 5 2.5            an explicit box (world x0 y0 z0 x1 y1 z1)
  cristal build-db scan.ply --out db.npz --roi-polygon 0,0 6,0 6,5 0,5       a floor-plan outline (heights above the floor)

Renders a cubemap (4 horizontal faces, or --faces all) with the neural renderer at each position
in free space, extracts XFeat features with the scan's 3D points behind them, and writes the
database atomically (versioned .npz). Beside it, DB.png: the positions seen from above over the
scan (are they where cameras go? positions missing from a room, or on top of shelves, show there).
"""

LOC_EPILOG = """\
examples:
  cristal localize site/scan.ply site/seq_00 --method rm --db site/reloc.npz --out traj.txt
  cristal localize scan.ply walk.mp4 --method rm --db db.npz --out traj.txt --frames 200
  cristal localize site/scan.ply site/seq_00 --method rm --db site/reloc.npz --odometry vio.txt --out traj.txt
  cristal localize site/map site/seq_00 --method pnl --map site/map --out traj.txt     Prebuild & Localize (CPU, no torch)
  cristal localize scan.ply walk.mp4 --method rm --db db.npz --out traj.txt --backfill    offline: also the frames
                                                                              before the first place it could tell apart
  cristal localize scan.ply robot/ --method rm --db db.npz --out traj.txt --near 12.5 3.0 1.2 3    started within 3 m
                                                                              of its dock (a site of look-alike aisles)

Writes a TUM trajectory (camera-to-world in the scan frame; frames without a pose are absent) and,
beside it, TRAJ.frames.csv: every frame's status, inliers, predicted 1-sigma (cm, deg: what a filter
fusing the poses should weigh them by), what solved the pose (features / direct / fused) and why a
LOST frame has no pose ('cristal eval' checks the 1-sigmas against ground truth), and TRAJ.png: the
poses seen from above over the scan (rm) or the map's landmarks (pnl), with the viewing direction,
relocalizations and each LOST stretch (and the ground truth when the sequence has one): the first
thing to look at after a recording. Prints
frames localized, relocalizations and FPS per stage, the LOST frames by reason (Render & Match: "ambiguous place" in a repetitive site, where a prior would help;
"pose too uncertain to report"; ...) and, when the sequence has a groundtruth.txt, the APE against
it. Ends with a one-line JSON summary.
"""


def add_gate_arguments(p: argparse.ArgumentParser) -> None:
    """The report gates, shared by ``cristal localize`` and ``cristal serve``: what a pose must meet to be reported
    (docs/TROUBLESHOOTING.md: 'pose too uncertain to report', 'render disagrees with the frame')."""
    p.add_argument("--max-sigma-deg", type=float, default=0.1,
                   help="report a pose only if its predicted 1-sigma orientation error is below this (default 0.1; scaled "
                        "up for cameras coarser than VGA); larger: more frames, less accurate")
    p.add_argument("--max-sigma-cm", type=float, default=1.0,
                   help="the same for the camera centre, in centimetres (default 1)")
    p.add_argument("--scan-sigma-mm", type=scan_sigma_arg, default="auto", metavar="MM",
                   help="the scan's registration error, 1-sigma in millimetres (the registration report's cloud-to-cloud "
                        "or bundle error; 0: a perfect scan). Default 'auto': what build-db or prebuild measured of "
                        "the scan ('cristal scan check'), 0 where the scan could not tell. No camera is placed better "
                        "than the scan: each reported 1-sigma counts it (a camera between stations that disagree by MM "
                        "turns by about MM / the distance to what it sees), so a pose beyond 3 sigma means what it "
                        "says. Not a gate: the same frames are reported")
    p.add_argument("--min-agreement", type=float, default=0.6, metavar="A",
                   help="(rm) a relocalization far from the last pose, or cold, needs its render to agree with the frame "
                        "this well (gradient correlation, -1..1; default 0.6; true places score 0.74-0.92 in the simulator's "
                        "office walks, identical aisles 8 m over 0.64-0.86; taken 0.75 times for a scan grey from the "
                        "laser's intensity, whose renders agree less): lower it if a real site's cold starts are "
                        "refused 'render disagrees with the frame'")


def rm_gates(args) -> dict:
    """RMConfig's fields for the gates of :func:`add_gate_arguments`."""
    return dict(max_sigma_deg=args.max_sigma_deg, max_sigma_m=args.max_sigma_cm / 100,
                reloc_min_agreement=args.min_agreement, scan_sigma_m=scan_sigma_m(args), scan_grid=scan_grid(args))


def scan_sigma_arg(text: str) -> float | str:
    """argparse type of ``--scan-sigma-mm``: millimetres, 0 to 1000, or ``auto`` (measured from the scan)."""
    import math

    if text == "auto":
        return text
    try:
        mm = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(mm) and 0.0 <= mm <= 1000.0):
        raise argparse.ArgumentTypeError(f"must be between 0 and 1000 millimetres, got {text}")
    return mm


def scan_sigma_m(args) -> float:
    """``--scan-sigma-mm`` in metres, after :func:`resolve_scan_sigma` (0 when the command has no such flag, or
    ``auto`` was not resolved)."""
    mm = getattr(args, "scan_sigma_mm", 0.0) or 0.0
    return 0.0 if mm == "auto" else float(mm) / 1000.0


def scan_grid(args):
    """Where on the site the scan's error lies (a :class:`services.localize.scan_error.DisagreementGrid`), as
    :func:`resolve_scan_sigma` found it (``auto`` only; else None)."""
    return getattr(args, "scan_grid", None)


def resolve_scan_sigma(args, scan=None, db_meta: dict | None = None, map_dir=None) -> None:
    """``--scan-sigma-mm auto`` (the default) into millimetres, and where on the site it lies into ``args.scan_grid``
    (each pose counts it where its camera looks, :func:`services.localize.scan_error.local_scan_sigma`): what
    ``cristal build-db`` recorded in the database (``db_meta``) or ``cristal prebuild`` beside the map (``map_dir``),
    else measured from ``scan`` itself (:func:`services.localize.scan_error.measure_scan`), else 0 (a scan that cannot
    tell: one station, or a file that does not say which points each station has). A number given keeps to itself."""
    if getattr(args, "scan_sigma_mm", None) != "auto":
        return
    from services.localize.scan_error import grid_arg, measure_scan, read_accuracy

    mm, source, record = None, None, None
    if db_meta is not None and db_meta.get("scan_sigma_mm") is not None:
        mm, source, record = float(db_meta["scan_sigma_mm"]), "the database", {"grid": db_meta.get("scan_grid")}
    elif map_dir is not None and (record := read_accuracy(map_dir)) is not None:
        mm, source = record["scan_sigma_mm"], "the map"
    elif scan is not None and db_meta is not None and "scan_sigma_mm" in db_meta:
        source = "the database (unknown)"  # build-db measured this scan and could not tell: no need to again
    elif scan is not None:
        record = measure_scan(scan)
        mm, source = record["scan_sigma_mm"], "the scan"
    args.scan_sigma_mm = mm or 0.0
    args.scan_grid = grid_arg(record) if mm else None
    if mm is None:
        log.info("--scan-sigma-mm auto: the scan's registration error is unknown (%s); each 1-sigma is the frame's own",
                 source or "nothing recorded it")
    else:
        log.info("--scan-sigma-mm auto: the scan's stations disagree by %.1f mm (from %s), counted in each 1-sigma",
                 mm, source)


def register(sub) -> None:
    from services.cli import add_odometry_args

    b = sub.add_parser("build-db", help="build the relocalization database of a scan (XFeat on cubemap renders)",
                       description="Build the Render & Match relocalization database.", epilog=DB_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    b.add_argument("scan", help="scan file (.ply .e57 .las .laz)")
    b.add_argument("--out", required=True, help="database file (.npz)")
    b.add_argument("--spacing", type=float, default=1.0, help="metres between positions (default 1.0)")
    b.add_argument("--heights", type=float, nargs="+", default=[1.5], help="camera heights above the floor (default 1.5)")
    b.add_argument("--margin", type=float, default=0.5, help="free space around each position in metres (default 0.5)")
    b.add_argument("--roi", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), help="box in world coordinates")
    b.add_argument("--roi-polygon", nargs="+", metavar="X,Y",
                   help="floor-plan outline in world x,y (>= 3 vertices); positions at --heights above the floor inside it")
    b.add_argument("--face-size", type=int, default=320,
                   help="pixels per 90-degree cubemap face (default 320; 480 relocalizes close-ups better, but in a sparse "
                        "scan of identical rack bays it matched a bay 4 m on)")
    b.add_argument("--faces", choices=["horizontal", "all"], default="horizontal",
                   help="cubemap faces rendered at each position: the 4 horizontal ones (default) or all 6 (floor and ceiling too)")
    b.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    b.set_defaults(func=run_build_db)

    p = sub.add_parser("localize", help="localize a camera sequence in a scan (writes a TUM trajectory)",
                       description="Localize every frame of a sequence in the scan's frame.", epilog=LOC_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scan", help="scan file (.ply .e57 .las .laz); with --method pnl the map folder will do")
    p.add_argument("sequence", help="sequence folder (rgb.txt + camera.json) or video file")
    p.add_argument("--method", choices=["rm", "pnl"], default="rm",
                   help="rm: Render & Match (needs --db); pnl: Prebuild & Localize against a prebuilt map (needs --map)")
    p.add_argument("--db", help="relocalization database from 'cristal build-db' (--method rm)")
    p.add_argument("--map", help="map folder from 'cristal prebuild' (--method pnl); the scan argument may then be the map too")
    p.add_argument("--out", required=True, help="output TUM trajectory")
    p.add_argument("--camera", help="camera.json to use instead of the sequence's own (a TUM RGB-D download has none; "
                                    "'cristal calibrate' writes a refined one)")
    p.add_argument("--frames", type=int, help="only the first N frames")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    p.add_argument("--max-side", type=int, help="XFeat input size (default: 480 on the CPU, full size on CUDA)")
    add_gate_arguments(p)
    p.add_argument("--no-align", action="store_true",
                   help="(--method pnl) skip the landmark-patch alignment and direct tracking: keypoints only, as for a map "
                        "without patches (office: 2.3 cm / 0.34 deg at 18 ms a frame, against 0.6 cm / 0.06 deg at 9 ms)")
    p.add_argument("--no-direct", action="store_true",
                   help="track with features on every frame (XFeat for rm, ORB then patch alignment for pnl) instead of "
                        "aligning the frame to patches straight from the prediction first: slower; for comparisons")
    p.add_argument("--supersample", type=int, metavar="K",
                   help="(--method rm) render keyframes at K times their resolution and pool them (default 2): the "
                        "scan's points land within 1/(2K) of a pixel, edges between them, and the frame aligns closer "
                        "to the truth; 1 renders ~1.5x faster on the CPU, less accurately")
    add_odometry_args(p, "each frame's motion since the previous one predicts it, and carries the pose through LOST "
                         "frames (up to 5 s) so tracking resumes without relocalizing")
    p.add_argument("--backfill", action="store_true",
                   help="offline: after the pass in time order, track backwards from the first pose after each LOST "
                        "stretch (frames recorded before the camera saw a place it could tell apart, e.g. an aisle of "
                        "identical racks). Same gates; a stretch is kept only if its track back lands on the pose "
                        "before it. The summary's 'backfilled' counts them; FPS then covers both passes")
    p.add_argument("--near", type=float, nargs=4, metavar=("X", "Y", "Z", "R"),
                   help="where the first frame was taken, roughly: within R metres of world (X, Y, Z) (a dock, an "
                        "entrance). Until the first pose, relocalization searches only as far from there as the camera "
                        "can have gone (3 m/s), so a look-alike place elsewhere (identical aisles) does not make the "
                        "start ambiguous")
    p.add_argument("--rolling-shutter", type=float, default=0.0, metavar="MS",
                   help="the camera's rolling-shutter readout, first row to last, in milliseconds (phones: 10-30; "
                        "default 0, a global shutter). Frames are re-sampled as if read at their middle row's time "
                        "from the tracked turn rate; poses and stamps are the middle row's. Without it, a phone's "
                        "fast turns cost centimetres and tenths of a degree")
    p.add_argument("--no-camera-check", action="store_true",
                   help="(--method rm) skip the check, after localizing, that the frames agree with their camera.json "
                        "(a fit of the intrinsics on up to 12 localized frames; a few seconds)")
    p.set_defaults(func=run_localize)

    c = sub.add_parser("calibrate", help="refine a camera's intrinsics (fx, fy, cx, cy) against the scan",
                       description="Refine a camera's focal lengths and principal point from a sequence localized in the "
                                   "scan (Render & Match): the scan is the calibration target. Poses are no better "
                                   "than the intrinsics: 1 % of focal length and 3 px of principal point cost 4 cm / "
                                   "0.4 deg on the office walk, and the pose gates cannot see it. The lens distortion "
                                   "is kept as given.", epilog=CAL_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("scan", help="scan file (.ply .e57 .las .laz)")
    c.add_argument("sequence", help="sequence folder (rgb.txt + camera.json) or video file")
    c.add_argument("--db", required=True, help="relocalization database from 'cristal build-db'")
    c.add_argument("--camera", help="the camera to start from (camera.json; default: the sequence's)")
    c.add_argument("--out", required=True, help="refined camera.json (written atomically)")
    c.add_argument("--every", type=int, default=10, help="use every N-th localized frame (default 10)")
    c.add_argument("--frames", type=int, help="only the first N frames")
    c.add_argument("--rounds", type=int, default=2, help="track-and-fit rounds (default 2)")
    c.add_argument("--distortion", action="store_true", help="fit the radial distortion k1 too (k2 and the rest kept as given)")
    c.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    c.set_defaults(func=run_calibrate)


CAL_EPILOG = """examples:
  cristal calibrate site/scan.ply site/seq_00 --db reloc.npz --out camera.json
  cristal calibrate scan.e57 phone.mp4 --camera phone.json --db reloc.npz --out phone-refined.json --every 5

Each round localizes the sequence with the camera as estimated so far, collects XFeat correspondences
(frame pixel <-> scan point) on every N-th localized frame and fits fx, fy, cx, cy to all of them.
Prints each round's camera and fit, ends with a one-line JSON summary. The frames should see the
scan at several depths and fill the view (a walk through the site, not a wall). Use the result
everywhere the camera is named: the frames' camera.json, 'cristal prebuild --camera' (a P&L map is
built for one camera), and the intrinsics a client sends with its frames.
"""


def run_calibrate(args) -> int:
    from services.cli import CliError
    from services.geometry.camera import Camera
    from services.io.scans import load_scan
    from services.io.sequence import open_sequence
    from services.localize.calibrate import calibrate
    from services.localize.render_match import RenderMatchTracker, RMConfig
    from services.log import progress
    from services.relocalize.database import RelocDB
    from services.render.renderer import Renderer

    _torch_threads()
    start = Camera.load(args.camera) if args.camera else None
    seq = open_sequence(args.sequence, camera=start)
    db = RelocDB.load(args.db)
    renderer = Renderer(load_scan(args.scan), device=args.device)
    ext = _tracking_extractor(renderer)
    n = min(len(seq), args.frames or len(seq))
    if args.every < 1 or args.rounds < 1:
        raise CliError("--every and --rounds must be at least 1")

    def track(camera):
        tr = RenderMatchTracker(renderer, ext, db, RMConfig())
        k = 0
        for i, f in enumerate(progress(seq.frames(tolerant=True), "calibrating", total=n, unit="frame")):
            if i >= n:
                break
            if f.image is None:  # missing or broken file (logged)
                continue
            r = tr.process(f.image, camera, stamp=seq.seconds(f.stamp))
            if r.T_wc is not None:
                k += 1
                if k % args.every == 1 or args.every == 1:
                    yield tr.correspondences(f.image, camera, r.T_wc)

    try:
        res = calibrate(track, seq.camera, rounds=args.rounds, distortion=args.distortion)
    except ValueError as e:
        raise CliError(f"cannot calibrate: {e}. Localize more of the sequence (check --db; --every 1; a starting "
                       f"camera nearer the truth)") from e
    res.camera.save(args.out)
    c0, c1 = seq.camera, res.camera
    print(f"fx {c0.fx:.2f} -> {c1.fx:.2f}, fy {c0.fy:.2f} -> {c1.fy:.2f}, cx {c0.cx:.2f} -> {c1.cx:.2f}, "
          f"cy {c0.cy:.2f} -> {c1.cy:.2f}, distortion {list(c0.distortion)} -> {[round(x, 4) for x in c1.distortion]} "
          f"from {res.frames} frames, {res.points} correspondences, {res.rms_px:.2f} px RMSE")
    print(json.dumps({"out": str(args.out), "fx": c1.fx, "fy": c1.fy, "cx": c1.cx, "cy": c1.cy,
                      "distortion": list(c1.distortion), "frames": res.frames,
                      "points": res.points, "rms_px": res.rms_px, "rounds": res.rounds}))
    return 0


def _tracking_extractor(renderer, max_side: int | None = None):
    """XFeat as Render & Match tracks with it: 1024 keypoints on frames at most ``max_side`` px (default: 480 on the
    CPU, the full frame on CUDA)."""
    from services.features.xfeat import XFeatExtractor

    return XFeatExtractor(device=str(renderer.device), top_k=1024,
                          max_side=max_side or (None if renderer.device.type == "cuda" else 480))


def _torch_threads() -> None:
    import os

    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))  # 1 unless -j: faster on a loaded 2-core box


def run_build_db(args) -> int:
    from services.cli import emit_summary, positions_picture, roi_polygon
    from services.features.xfeat import XFeatExtractor
    from services.io.scans import load_scan
    from services.localize.scan_error import describe, measure_scan
    from services.relocalize.database import DBConfig, build_database
    from services.relocalize.roi import RoiConfig, sample_positions
    from services.render.renderer import Renderer

    _torch_threads()
    scan = load_scan(args.scan)
    pos = sample_positions(scan, RoiConfig(spacing=args.spacing, heights=tuple(args.heights), margin=args.margin,
                                           box=tuple(args.roi) if args.roi else None,
                                           polygon=roi_polygon(args.roi_polygon) if args.roi_polygon else None))
    if len(pos) == 0:
        raise ValueError("no position in free space inside the region of interest: check --roi, --heights, --margin")
    renderer = Renderer(scan, device=args.device)
    ext = XFeatExtractor(device=str(renderer.device))
    src = __import__("pathlib").Path(args.scan)
    accuracy = measure_scan(scan)  # the scan's own error, for --scan-sigma-mm auto where the scan is not measured
    db = build_database(renderer, pos, ext, DBConfig(face_size=args.face_size, faces=args.faces),
                        meta={"scan": str(src), "scan_bytes": src.stat().st_size, "spacing": args.spacing,
                              "scan_sigma_mm": accuracy["scan_sigma_mm"], "scan_grid": accuracy["grid"]})
    db.save(args.out)
    print(f"database {args.out}: {db.meta['positions']} positions, {db.n_views} views, {db.meta['features']:,} features "
          f"in {db.meta['build_seconds']} s; {describe(accuracy)}")
    plural = "s" * (len(pos) != 1)
    picture = positions_picture(pos, args.out, scan=scan, label="database positions",
                                title=f"relocalization database: {len(pos)} position{plural}, {args.spacing:g} m apart "
                                      f"(top view)")
    emit_summary({"out": args.out, "picture": picture and str(picture),
                  **{k: db.meta[k] for k in ("positions", "views", "features", "build_seconds", "scan_sigma_mm")}})
    return 0


def run_localize(args) -> int:
    from services.cli import CliError, near_arg

    if not 0 <= args.rolling_shutter <= 200:
        raise CliError(f"--rolling-shutter is the readout in milliseconds, 0 to 200 (got {args.rolling_shutter:g})")
    near_arg(args.near)  # (a bad hint fails before anything loads; the runner takes it from args)
    if getattr(args, "supersample", None) is not None and not 1 <= args.supersample <= 4:
        raise CliError(f"--supersample is a whole factor from 1 (off) to 4, got {args.supersample}")
    if args.method == "pnl":
        from services.localize.pnl_cli import run_localize_pnl

        return run_localize_pnl(args)
    if not args.db:
        raise CliError("--method rm needs --db (a relocalization database from 'cristal build-db')")
    from services.geometry.camera import Camera
    from services.io.scans import load_scan
    from services.io.sequence import open_sequence
    from services.io.trajectory import read_odometry
    from services.localize.render_match import RenderMatchTracker, RMConfig
    from services.localize.runner import localize_and_report
    from services.relocalize.database import RelocDB
    from services.render.renderer import Renderer

    _torch_threads()
    seq = open_sequence(args.sequence, camera=Camera.load(args.camera) if args.camera else None)
    odometry = read_odometry(args.odometry, seq.stamps, axes=args.odometry_axes) if args.odometry else None
    db = RelocDB.load(args.db)
    scan = load_scan(args.scan)
    resolve_scan_sigma(args, scan, db.meta)
    renderer = Renderer(scan, device=args.device)
    cfg = RMConfig(**rm_gates(args),
                   direct_points=0 if getattr(args, "no_direct", False) else RMConfig().direct_points,
                   readout_s=getattr(args, "rolling_shutter", 0.0) / 1000.0,
                   keyframe_supersample=getattr(args, "supersample", None) or RMConfig().keyframe_supersample)
    tracker = RenderMatchTracker(renderer, _tracking_extractor(renderer, args.max_side), db, cfg)
    return localize_and_report(tracker, seq, args, args.method, stamped=True, odometry=odometry,
                               background={"scan": scan},
                               after=None if getattr(args, "no_camera_check", False) else lambda traj: _camera_check(tracker, seq, traj))


def _camera_check(tracker, seq, traj) -> dict:
    """Do the frames agree with their camera.json? (services.localize.calibrate.check_camera)"""
    import logging

    from services.localize.calibrate import check_camera

    try:
        c = check_camera(tracker, seq, traj)
    except ValueError as e:
        print(f"camera check: not done ({e})")
        return {"camera_check": None}
    cam = seq.camera
    line = (f"camera check: the frames imply fx {c['fx']:.1f} fy {c['fy']:.1f} cx {c['cx']:.1f} cy {c['cy']:.1f} "
            f"(given {cam.fx:.1f} {cam.fy:.1f} {cam.cx:.1f} {cam.cy:.1f}; {c['frames']} frames, {c['points']} points)")
    if c["ok"]:
        print(line + ": consistent")
    else:
        print(line)
        logging.getLogger("cristal").warning(
            "the camera's intrinsics look wrong (focal length %.1f %% off, principal point %.1f px): poses absorb this "
            "unseen (1 %% of focal length cost 4 cm on the office walk); run 'cristal calibrate'",
            100 * c["focal_off"], c["centre_off_px_at_640"])
    return {"camera_check": c}
