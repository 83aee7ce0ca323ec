"""``cristal stream``: a sequence, video or camera through the service, with on-device fallback."""

from __future__ import annotations

import argparse

EPILOG = """\
examples:
  cristal stream site/seq_00 --out traj.txt                      server on this machine (tcp/127.0.0.1:7447)
  cristal stream site/seq_00 --out traj.txt --map site/pnl        + local P&L fallback from a map directory
  cristal stream walk.mp4 --out traj.txt --map download --fps 30  fetch the P&L bundle over Zenoh into ./download
  cristal stream 0 --camera cam.json --out live.txt --connect tcp/10.0.0.2:7447 --site hq --map-id floor2

Writes the TUM trajectory (camera-to-world, scan frame) and TRAJ.sources.txt with the source of
every pose: 'server', 'local' (the P&L fallback: server unreachable, deadline missed or lost) or '-',
and TRAJ.png: the poses seen from above (the fallback's marked; over its map's landmarks with --map).
With --map DIR: a DIR holding map.msg is used as is; otherwise the bundle is downloaded into DIR.
"""


def register(sub) -> None:
    from services.cli import add_odometry_args
    from services.localize.cli import scan_sigma_arg

    p = sub.add_parser("stream", help="stream a sequence / video / camera to the server (with local P&L fallback)",
                       description="Localize a sequence through the cristal service over Zenoh.", epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", help="sequence folder, video file, or an OpenCV camera index (needs --camera)")
    p.add_argument("--out", required=True, help="output TUM trajectory")
    p.add_argument("--map", dest="map_dir", metavar="MAPDIR", help="P&L map for the local fallback (path, or where to download it)")
    p.add_argument("--scan-sigma-mm", type=scan_sigma_arg, default="auto", metavar="MM",
                   help="the scan's registration error (1-sigma, mm), counted in the local fallback's reported 1-sigma "
                        "as the server's --scan-sigma-mm counts it in its own (default 'auto': what prebuild recorded "
                        "beside the map)")
    p.add_argument("--camera", help="camera.json (for a live camera or a video without one)")
    p.add_argument("--client-id", help="this device's id (default: random)")
    p.add_argument("--site", default="default", help="site id the server serves (key scope, default 'default')")
    p.add_argument("--map-id", default="default", help="map id within the site (key scope, default 'default')")
    p.add_argument("--rolling-shutter", type=float, default=0.0, metavar="MS",
                   help="the camera's rolling-shutter readout, first row to last, in ms (phones: 10-30; default 0, a "
                        "global shutter): the server and the local fallback undo it from the tracked motion")
    p.add_argument("--near", type=float, nargs=4, metavar=("X", "Y", "Z", "R"),
                   help="where the stream starts, roughly: within R metres of world (X, Y, Z) (a dock, an entrance); "
                        "sent until the first pose, so a start among look-alike places (identical aisles) is not "
                        "ambiguous")
    p.add_argument("--deadline", type=float, default=200.0, help="ms to wait for each pose before using the local one (default 200)")
    p.add_argument("--fps", type=float, default=0.0, help="pace frames at this rate (default: as fast as replies come)")
    p.add_argument("--frames", type=int, help="only the first N frames")
    add_odometry_args(p, "for a recorded sequence: each frame goes with its motion since the previous one, which the "
                         "server and the local fallback predict from and carry the pose on by through LOST frames")
    p.add_argument("--wait", type=float, default=5.0, help="seconds to wait for a server before the first frame (default 5)")
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 configuration")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="connect endpoint (default tcp/127.0.0.1:7447)")
    p.set_defaults(func=run_stream)


class _Camera:
    """An OpenCV camera as a sequence (stamps are wall-clock seconds)."""

    def __init__(self, index: int, camera, frames: int | None):
        import cv2

        self.cap = cv2.VideoCapture(index)
        if not self.cap.isOpened():
            raise FileNotFoundError(f"camera {index} cannot be opened")
        self.camera, self.n, self.files, self.groundtruth = camera, frames or 10 ** 9, None, None

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        return self.frames()

    def frames(self, tolerant: bool = False):
        import time

        from services.io.sequence import Frame

        for _ in range(self.n):
            ok, img = self.cap.read()
            if not ok:
                break
            yield Frame(f"{time.time():.6f}", img)
        self.cap.release()


def run_stream(args) -> int:
    from pathlib import Path

    from services.cli import CliError, emit_summary, near_arg
    from services.client.client import LocalizationClient

    if not 0 <= args.rolling_shutter <= 200:
        raise CliError(f"--rolling-shutter is the readout in milliseconds, 0 to 200 (got {args.rolling_shutter:g})")
    near = near_arg(args.near)
    from services.client.fallback import load_local
    from services.client.stream import sources_path, stream_sequence
    from services.geometry.camera import Camera
    from services.io.sequence import open_sequence
    from services.localize.cli import scan_sigma_m
    from services.zconfig import make_config

    cam = Camera.load(args.camera) if args.camera else None
    if args.sequence.isdigit() and not Path(args.sequence).exists():
        if cam is None:
            raise CliError("a live camera needs --camera camera.json")
        seq = _Camera(int(args.sequence), cam, args.frames)
    else:
        seq = open_sequence(args.sequence, camera=cam) if cam else open_sequence(args.sequence)
    odometry = None
    if args.odometry:
        from services.io.trajectory import read_odometry

        if isinstance(seq, _Camera):
            raise CliError("--odometry is for a recorded sequence; a live device sends its motion with each frame "
                           "(LocalizationClient.localize(..., motion=...))")
        odometry = read_odometry(args.odometry, seq.stamps, axes=args.odometry_axes)
    client = LocalizationClient(make_config(args.zenoh_config, connect=args.connect), client_id=args.client_id,
                                site=args.site, map_id=args.map_id, deadline_ms=args.deadline)
    try:
        if not client.wait_for_server(args.wait):
            print(f"no server for site {args.site!r} map {args.map_id!r} yet: starting on the local fallback", flush=True)
        fallback = None
        if args.map_dir:
            d = Path(args.map_dir)
            if not (d / "map.msg").is_file():
                d = client.download_bundle(d)
                print(f"P&L map bundle downloaded to {d}", flush=True)
            fallback = load_local(d, None if args.scan_sigma_mm == "auto" else scan_sigma_m(args))
        traj, st = stream_sequence(seq, client, fallback, args.out, frames=args.frames, fps=args.fps, odometry=odometry,
                                   readout_s=args.rolling_shutter / 1000.0 or None,
                                   near=near)
    finally:
        client.close()
    s = st.summary()
    posed = st.server + st.local  # (every frame's: the trajectory in memory is the last ones' on a long live stream)
    print(f"{posed}/{st.frames} frames with a pose: {st.server} from the server, {st.local} local "
          f"({st.missed} missed deadlines, {st.lost} lost, {st.switches} worker switches); {s['fps']} FPS, "
          f"round trip p50 {s['rtt_p50_ms']} ms p99 {s['rtt_p99_ms']} ms; sources in {sources_path(args.out)}")
    if st.picture is not None:
        print(f"picture: {st.picture} (the poses seen from above)")
    summary = {"out": args.out, "poses": posed, "odometry": odometry is not None,
               "picture": st.picture and str(st.picture), **s}
    gt = getattr(seq, "groundtruth", None)
    if gt is not None and posed:
        if st.forgotten:  # (a recording longer than memory keeps: the file has every pose)
            from services.io.trajectory import read_tum

            traj = read_tum(args.out)
        from services.eval.ape import ape_first_frames

        line, fields = ape_first_frames(gt, traj, st.frames)
        print(line)
        summary.update(fields)
    emit_summary(summary)
    return 130 if st.interrupted else 0 if posed else 1  # (130: ended by Ctrl-C, as a shell reports it)
