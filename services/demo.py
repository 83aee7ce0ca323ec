"""``cristal demo``: the whole loop on the embedded simulated site, over real Zenoh sessions.

1. **simulate** the default office site (a LiDAR scan + a hand-held camera sequence with ground
   truth); reused when ``--site`` is given or the output folder already holds a matching one;
2. **build** the Render & Match relocalization database and the Prebuild & Localize (P&L) map from
   the scan alone (reused while the scan and the settings are unchanged);
3. **serve**: a Zenoh router and the localization server (Render & Match, sharing the renderer
   built in step 2) start in this process on a free loopback port;
4. **stream** the sequence through the client library on its own Zenoh session, as a headset would:
   the client downloads the P&L map bundle over Zenoh, sends every frame with a deadline, and uses
   the server's pose, or its local P&L pose when the server misses the deadline or is lost;
   a subscriber stands in for a fleet dashboard and counts the published poses;
5. **score**: APE against ground truth (no alignment and SE(3)), FPS, round-trip latency, where
   the poses came from; an overlay picture (each camera frame blended with the neural render of
   the scan at its estimated pose: misalignment shows as ghosting) and the trajectory plots.

Every session is closed on the way out, also on errors and Ctrl-C (or SIGTERM).
"""

from __future__ import annotations

import argparse
import logging

log = logging.getLogger("cristal.demo")

EPILOG = """\
examples:
  cristal demo --out runs/demo                     the whole loop on the simulated office site (a few minutes on 2 cores)
  cristal demo --out runs/demo --frames 60         stream only the first 60 frames
  cristal demo --out runs/demo --site my/site      an existing site folder (scan.ply + seq_00/ with groundtruth.txt)
  cristal demo --out runs/demo --keep-server --port 7447
                                                   keep the router + server up afterwards; in another shell:
                                                   cristal stream runs/demo/site/seq_00 --out t.txt --map pnl-cache

writes OUT/site/ (the simulated site), OUT/reloc.npz and OUT/pnl/ (database and P&L map),
OUT/estimate.txt (TUM) + OUT/estimate.sources.txt (server/local per frame) + OUT/estimate.png (the poses
from above, the local fallback's marked), OUT/overlay.jpg,
OUT/plots/trajectory.png and OUT/plots/errors.png, and ends with a one-line JSON summary.
"""

SERVER_ID = "demo-worker"
CLIENT_ID = "demo-camera"
OVERLAY_TILES = 6


def register(sub) -> None:
    p = sub.add_parser("demo", help="the whole loop on the embedded simulated site: simulate, build, serve, stream, score",
                       description=__doc__, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--site", help="an existing site folder (scan.ply + SEQUENCE/); default: simulate one into OUT/site")
    p.add_argument("--sequence", default="seq_00", help="sequence folder inside the site (default seq_00)")
    p.add_argument("--frames", type=int, help="stream only the first N frames (default: all; a simulated sequence "
                   "keeps the preset's full length, 300 frames for the office, so it is simulated once and reused)")
    p.add_argument("--preset", default="office", choices=["office", "warehouse"], help="simulated site (default office)")
    p.add_argument("--seed", type=int, default=1, help="simulation seed (default 1)")
    p.add_argument("--lidar-step", type=float, dest="lidar_step_deg", help="simulated scanner's angular step in degrees")
    p.add_argument("--regenerate", action="store_true", help="simulate and build again even if OUT holds matching results")
    p.add_argument("--db-spacing", type=float, default=1.0, help="metres between relocalization database positions (default 1.0)")
    p.add_argument("--map-spacing", type=float, default=1.0, help="metres between P&L map positions (default 1.0)")
    p.add_argument("--deadline", type=float, default=1000.0,
                   help="ms the client waits for the server's pose before using its local one (default 1000: a CPU server)")
    p.add_argument("--port", type=int, default=0, help="router port on 127.0.0.1 (default: a free one)")
    p.add_argument("--keep-server", action="store_true", help="keep the router and server running afterwards (Ctrl-C stops)")
    p.add_argument("--device", default="auto", help="renderer/XFeat device (default: CUDA if available)")
    p.add_argument("--odometry", nargs="?", const="sim", metavar="TUM",
                   help="stream with the device's own odometry, as a headset's VIO or a robot's wheels give it: the server "
                        "and the local fallback predict from it and carry the pose through LOST frames. Alone: simulated "
                        "from the sequence's ground truth (services/sim/odometry.py: 0.03 deg and 1 %% of the step of noise "
                        "per frame, 1 %% scale bias); or a TUM trajectory on the frames' clock (interpolated at each frame)")
    p.set_defaults(func=run)


# ---- steps ---------------------------------------------------------------------------------------
def prepare_site(args, out):
    """The site folder: ``--site`` as is, or the simulated preset in OUT/site (simulated unless it matches)."""
    import json
    from dataclasses import asdict
    from pathlib import Path

    from services.cli import CliError
    from services.sim.site import _jsonable, config_for, generate_site

    if args.site:
        site = Path(args.site)
        if not site.is_dir():
            raise CliError(f"--site {site}: no such folder")
        log.info("[1/5] site %s (given, not simulated)", site)
        return site, False
    site = out / "site"
    cfg = config_for(args.preset, seed=args.seed, lidar_step_deg=args.lidar_step_deg)
    meta = site / "site.json"
    if not args.regenerate and meta.exists() and json.loads(meta.read_text()).get("config") == _jsonable(asdict(cfg)):
        log.info("[1/5] simulated %s site %s is up to date (--regenerate simulates it again)", args.preset, site)
        return site, False
    log.info("[1/5] simulating the %s site (seed %d) into %s", args.preset, args.seed, site)
    generate_site(cfg, site)
    return site, True


def find_scan(site):
    from services.cli import CliError

    for ext in ("ply", "e57", "las", "laz"):
        if (site / f"scan.{ext}").is_file():
            return site / f"scan.{ext}"
    raise CliError(f"{site}: no scan.ply / scan.e57 / scan.las / scan.laz")


def _stamp(scan_path, what: dict) -> dict:
    st = scan_path.stat()
    return {"scan": str(scan_path.resolve()), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns, **what}


def build_or_load_db(renderer, scan, scan_path, out, spacing: float, regenerate: bool, accuracy: dict | None = None):
    """The relocalization database in OUT/reloc.npz, as ``cristal build-db`` builds it (reused while it matches), with
    the scan's registration error (``accuracy``: :func:`services.localize.scan_error.measure_scan`) in its meta."""
    import json

    from services.features.xfeat import XFeatExtractor
    from services.io.atomic import atomic_write_text
    from services.relocalize.database import DBConfig, RelocDB, build_database
    from services.relocalize.roi import RoiConfig, sample_positions

    path, stamp_path = out / "reloc.npz", out / "reloc.build.json"
    cfg = DBConfig()
    stamp = _stamp(scan_path, {"spacing": spacing, "face_size": cfg.face_size, "faces": cfg.faces, "top_k": cfg.top_k})
    if not regenerate and path.is_file() and stamp_path.is_file() and json.loads(stamp_path.read_text()) == stamp:
        log.info("[2/5] relocalization database %s is up to date", path)
        return RelocDB.load(path), False
    pos = sample_positions(scan, RoiConfig(spacing=spacing))
    if len(pos) == 0:
        raise ValueError(f"{scan_path}: no position in free space for the relocalization database")
    log.info("[2/5] relocalization database: XFeat on cubemap renders at %d positions", len(pos))
    db = build_database(renderer, pos, XFeatExtractor(device=str(renderer.device)), cfg,
                        meta={"scan": str(scan_path), "scan_bytes": scan_path.stat().st_size, "spacing": spacing,
                              "scan_sigma_mm": (accuracy or {}).get("scan_sigma_mm"),
                              "scan_grid": (accuracy or {}).get("grid")})
    db.save(path)
    atomic_write_text(stamp_path, json.dumps(stamp, indent=1) + "\n")
    return db, True


def build_or_load_map(renderer, scan, scan_path, camera, out, spacing: float, regenerate: bool):
    """The P&L map in OUT/pnl/, as ``cristal prebuild`` builds it; None (with a warning) if it has no landmark."""
    import json
    import shutil

    from services.io.atomic import atomic_write_text
    from services.prebuild.builder import BuildConfig, build_map
    from services.prebuild.patches import PATCH_FILE
    from services.prebuild.stella_map import CONFIG_FILE, MAP_FILE, check_map_dict, map_to_dict, write_config, write_map
    from services.relocalize.roi import RoiConfig, sample_positions

    d, stamp_path = out / "pnl", out / "pnl.build.json"
    cfg = BuildConfig()
    stamp = _stamp(scan_path, {"spacing": spacing, "camera": camera.to_dict(), "max_keypoints": cfg.orb.max_keypoints,
                               "patch_size": cfg.patch_size})
    if not regenerate and (d / MAP_FILE).is_file() and stamp_path.is_file() and json.loads(stamp_path.read_text()) == stamp:
        log.info("[2/5] P&L map %s is up to date", d)
        return d, False
    stamp_path.unlink(missing_ok=True)
    pos = sample_positions(scan, RoiConfig(spacing=spacing))
    log.info("[2/5] P&L map: ORB keyframes and landmarks from renders at %d positions", len(pos))
    m, stats, patches = build_map(renderer, pos, camera, cfg, spacing=spacing) if len(pos) else (None, {}, None)
    if m is None or m.n_landmarks == 0:
        log.warning("the P&L map has no landmark (camera %dx%d): the client runs without a local fallback",
                    camera.width, camera.height)
        shutil.rmtree(d, ignore_errors=True)
        return None, True
    problems = check_map_dict(map_to_dict(m))
    if problems:  # our own writer broke a loader rule: a bug, never serve such a map
        raise RuntimeError("built map breaks stella_vslam loader rules: " + "; ".join(map(str, problems[:5])))
    d.mkdir(parents=True, exist_ok=True)
    write_map(m, d / MAP_FILE)
    write_config(d / CONFIG_FILE, m.cameras[cfg.camera_name], next(iter(m.orb_params.values())), cfg.orb.max_keypoints)
    if patches is not None:
        patches.save(d / PATCH_FILE)
    atomic_write_text(stamp_path, json.dumps(stamp, indent=1) + "\n")
    return d, True


def _odometry(arg: str | None, seq):
    """``--odometry``: None, simulated from the sequence's ground truth ("sim"), or a TUM file."""
    if arg is None:
        return None
    if arg != "sim":
        from services.io.trajectory import read_odometry

        return read_odometry(arg, seq.stamps)
    if seq.groundtruth is None:
        raise ValueError("--odometry alone simulates it from the sequence's groundtruth.txt, which this sequence lacks: "
                         "give the device's odometry as a TUM file")
    from services.sim.odometry import simulate_odometry

    return simulate_odometry(seq.groundtruth)


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def overlay_grid(renderer, seq, poses: dict, gt, out_path, tiles: int = OVERLAY_TILES, cols: int = 3,
                 alpha: float = 0.5, tile_width: int = 480):
    """Camera frames blended with the scan's neural render at their estimated poses, in a grid (JPEG).

    ``poses``: frame index -> (T_wc, source). Tiles spread over the frames that got a pose (one
    local-fallback frame among them if there is any), labelled with frame, source and the error
    against ground truth. A well-registered frame looks sharp; a pose error shows as ghosting.
    """
    import cv2
    import numpy as np

    from services.io.atomic import atomic_write_bytes

    idx = sorted(poses)
    if not idx:
        return None
    pick = [idx[int(round(k))] for k in np.linspace(0, len(idx) - 1, min(tiles, len(idx)))]
    local = [i for i in idx if poses[i][1] == "local"]
    if local and not any(poses[i][1] == "local" for i in pick) and len(pick) > 1:
        pick[-2 if len(pick) > 2 else -1] = local[len(local) // 2]
        pick = sorted(set(pick))
    out_tiles = []
    for i in pick:
        T, source = poses[i]
        frame = seq.read(i).image
        r = renderer.render(T, seq.camera)
        blend = cv2.addWeighted(frame, 1.0 - alpha, cv2.cvtColor(r.rgb, cv2.COLOR_RGB2BGR), alpha, 0.0)
        s = tile_width / blend.shape[1]
        tile = cv2.resize(blend, (tile_width, int(round(blend.shape[0] * s))), interpolation=cv2.INTER_AREA)
        label = f"frame {i}  {source}"
        if gt is not None and i < len(gt):
            dt, dr = gt.poses[i].distance_to(T)
            label += f"  {100 * dt:.1f} cm {dr:.2f} deg"
        (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        tile[:th + base + 10, :tw + 12] //= 3  # a dark band behind the label
        cv2.putText(tile, label, (6, th + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        out_tiles.append(tile)
    h, w = out_tiles[0].shape[:2]
    rows = -(-len(out_tiles) // cols)
    ncols = min(cols, len(out_tiles))
    grid = np.zeros((rows * h, ncols * w, 3), np.uint8)
    for k, t in enumerate(out_tiles):
        grid[(k // ncols) * h:(k // ncols + 1) * h, (k % ncols) * w:(k % ncols + 1) * w] = t[:h, :w]
    ok, buf = cv2.imencode(".jpg", grid, [cv2.IMWRITE_JPEG_QUALITY, 90])
    atomic_write_bytes(out_path, buf.tobytes())
    return out_path


class _Stop:
    """SIGTERM ends the demo through the normal clean-up path (every session closes); while the server is
    kept running, Ctrl-C (SIGINT) or SIGTERM ends the wait. Ctrl-C during the run raises KeyboardInterrupt,
    which unwinds the same way."""

    def __init__(self):
        import threading

        self.event = threading.Event()
        self._old: dict = {}
        self._main = threading.current_thread() is threading.main_thread()  # only it may set handlers

    def __enter__(self):
        import signal

        def on_term(signum, frame):
            self.event.set()
            raise SystemExit(128 + signum)  # unwinds through every 'finally': sessions close

        if self._main:
            self._old[signal.SIGTERM] = signal.signal(signal.SIGTERM, on_term)
        return self

    def wait_for_interrupt(self) -> None:
        import signal

        if self._main:
            self._old.setdefault(signal.SIGINT, signal.getsignal(signal.SIGINT))
            signal.signal(signal.SIGINT, lambda *_: self.event.set())
            signal.signal(signal.SIGTERM, lambda *_: self.event.set())
        while not self.event.wait(0.5):
            pass

    def __exit__(self, *exc):
        import signal

        for sig, h in self._old.items():
            signal.signal(sig, h)
        return False


class _Clock:
    """Wall and CPU seconds (all threads of this process: server, client, builds) per step."""

    def __init__(self):
        import time

        self.t0, self.c0 = time.perf_counter(), time.process_time()
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def step(self, name: str):
        import contextlib
        import time

        @contextlib.contextmanager
        def _step():
            t, c = time.perf_counter(), time.process_time()
            try:
                yield
            finally:
                self.wall[name] = time.perf_counter() - t
                self.cpu[name] = time.process_time() - c

        return _step()

    def total(self) -> tuple[float, float]:
        import time

        return time.perf_counter() - self.t0, time.process_time() - self.c0


# ---- the job -------------------------------------------------------------------------------------
def run(args) -> int:
    import contextlib
    import os
    import time
    from pathlib import Path

    from services.cli import CliError, emit_summary
    from services.io.sequence import open_sequence
    from services.io.trajectory import Trajectory

    clock = _Clock()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    with clock.step("simulate"):
        site, simulated = prepare_site(args, out)
    seq_dir = site / args.sequence
    if not seq_dir.is_dir():
        raise CliError(f"{seq_dir}: no such sequence folder")
    seq = open_sequence(seq_dir)
    if seq.groundtruth is None:
        raise CliError(f"{seq_dir}: no groundtruth.txt to score against")
    odometry = _odometry(args.odometry, seq)
    n = len(seq) if not args.frames else min(len(seq), args.frames)
    if n < 1:
        raise CliError("--frames must be at least 1")
    scan_path = find_scan(site)

    # ---- build: database + P&L map over one renderer (the server reuses it) --------------------
    import torch

    from services.io.scans import load_scan
    from services.localize.scan_error import describe, grid_arg, measure_scan, write_accuracy
    from services.render.renderer import Renderer

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))  # 1 unless -j: faster on a loaded 2-core box
    with clock.step("database"):
        scan = load_scan(scan_path)
        renderer = Renderer(scan, device=args.device)
        accuracy = measure_scan(scan)  # how far the scan's stations disagree: counted in each reported 1-sigma
        db, _ = build_or_load_db(renderer, scan, scan_path, out, args.db_spacing, args.regenerate, accuracy)
    with clock.step("pnl_map"):
        map_dir, _ = build_or_load_map(renderer, scan, scan_path, seq.camera, out, args.map_spacing, args.regenerate)
        if map_dir is not None:
            write_accuracy(map_dir, accuracy)  # as prebuild does (and a map reused from an earlier run gets it too)
    scan_sigma_mm = accuracy["scan_sigma_mm"] or 0.0
    log.info("[2/5] %s: counted in each pose's reported 1-sigma", describe(accuracy))

    # ---- serve + stream over Zenoh ----------------------------------------------------------------
    from protocol import keys
    from services.client.client import LocalizationClient
    from services.client.fallback import load_local
    from services.client.stream import sources_path, stream_sequence
    from services.localize.render_match import RMConfig
    from services.server.backend import RMBackend
    from services.server.service import LocalizationServer, ServerConfig
    from services.zconfig import make_config, open_session

    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    est_path = out / "estimate.txt"
    poses: dict[int, tuple] = {}
    published = {"n": 0}
    with _Stop() as stop, contextlib.ExitStack() as stack:
        with clock.step("service_start"):
            router = open_session(make_config(None, mode="router", listen=[endpoint], default_role="server"))
            stack.callback(router.close)
            server = LocalizationServer(RMBackend.from_loaded(scan, renderer, db,
                                                              cfg=RMConfig(scan_sigma_m=scan_sigma_mm / 1000.0,
                                                                           scan_grid=grid_arg(accuracy))),
                                        ServerConfig(server_id=SERVER_ID, idle_s=3600.0),
                                        make_config(None, connect=[endpoint], default_role="server"), bundle_dir=map_dir)
            server.start()
            stack.callback(server.close)

            def on_pose(sample) -> None:  # a fleet dashboard: every pose the server publishes
                published["n"] += 1

            dashboard = router.declare_subscriber(keys.poses(keys.DEFAULT_SITE), on_pose)
            stack.callback(dashboard.undeclare)
            client = LocalizationClient(make_config(None, connect=[endpoint]), client_id=CLIENT_ID, deadline_ms=args.deadline)
            stack.callback(client.close)
            if not client.wait_for_server(30.0):
                raise RuntimeError(f"the demo's server did not come up on {endpoint}")
            fallback, local_map = None, None
            if map_dir is not None:
                local_map = client.download_bundle(out / "client-cache")  # the P&L map bundle, over Zenoh
                fallback = load_local(local_map)
        log.info("[3/5] router on %s, server %s (Render & Match) and client %s%s", endpoint, SERVER_ID, CLIENT_ID,
                 f" with the P&L map downloaded to {local_map}" if fallback is not None else " (no local fallback)")

        log.info("[4/5] streaming %d frames of %s through the service (deadline %.0f ms)", n, seq_dir, args.deadline)

        def on_frame(i, frame, T, source, rep) -> None:
            if T is not None:
                poses[i] = (T, source)

        with clock.step("stream"):
            traj, st = stream_sequence(seq, client, fallback, est_path, frames=n, on_frame=on_frame,
                                       odometry=odometry)
            time.sleep(0.2)  # the last publication in flight

        # ---- score, overlay, plots ------------------------------------------------------------
        from services.eval.ape import compute_ape, evaluate
        from services.eval.plots import plot_errors, plot_trajectory_topdown

        log.info("[5/5] scoring against ground truth; overlay and plots")
        plots = out / "plots"
        with clock.step("score"):
            gt = seq.groundtruth
            gt_n = Trajectory(gt.stamps[:n], gt.poses[:n])
            results = evaluate(gt_n, traj, ("none", "se3")) if len(traj) else {}
            srv_traj = Trajectory()
            for i, (stamp, src, *_rest) in enumerate(st.rows):
                if src == "server" and i in poses:
                    srv_traj.append(stamp, poses[i][0])
            srv_ape = compute_ape(gt_n, srv_traj, "none") if len(srv_traj) else None
            overlay = overlay_grid(renderer, seq, poses, gt, out / "overlay.jpg")
            if len(traj):
                plot_trajectory_topdown(gt_n, traj, plots / "trajectory.png", scan=scan,
                                        title=f"{site.name if args.site else args.preset} {args.sequence}: ground truth "
                                              "vs the poses the client used")
                plot_errors(results["none"], plots / "errors.png")
        wall, cpu = clock.total()

        s = st.summary()
        lines = [f"cristal demo: {len(scan):,} scan points, {args.sequence} {n} frames "
                 f"{seq.camera.width}x{seq.camera.height}, server and client over Zenoh via a router on {endpoint}",
                 f"  poses: {len(traj)}/{n} frames: {st.server} from the server (Render & Match), {st.local} local "
                 f"(P&L fallback), {st.none} none; the server said lost {st.lost} times and missed {st.missed} deadlines; "
                 f"{published['n']} poses published"]
        for name, r in results.items():
            lines.append(f"  APE ({name:>4}): translation RMSE {100 * r.trans_rmse:.2f} cm, rotation RMSE "
                         f"{r.rot_rmse_deg:.3f} deg over {r.n_matched}/{r.n_gt} frames ({100 * r.fraction:.1f} %)")
        if srv_ape is not None and st.local:
            lines.append(f"  APE (none), server poses only: {100 * srv_ape.trans_rmse:.2f} cm, {srv_ape.rot_rmse_deg:.3f} deg")
        lines.append(f"  speed: {s['fps']} FPS end to end (one client, CPU server, next frame after the pose); round trip "
                     f"p50 {s['rtt_p50_ms']} ms, p99 {s['rtt_p99_ms']} ms (Zenoh + encoding p50 {s['overhead_p50_ms']} ms)")
        also = f", {st.picture.name}" if st.picture is not None else ""  # the client's top view
        lines.append(f"  wrote {est_path} (+ {sources_path(est_path).name}{also}), {overlay}, {plots / 'trajectory.png'}, "
                     f"{plots / 'errors.png'}")
        lines.append("  seconds (wall/CPU): " + ", ".join(f"{k} {clock.wall[k]:.0f}/{clock.cpu[k]:.0f}" for k in clock.wall)
                     + f"; total {wall:.0f}/{cpu:.0f}")
        print("\n".join(lines), flush=True)

        summary = {"site": str(site), "simulated": simulated, "points": len(scan), "scan_sigma_mm": scan_sigma_mm,
                   "sequence": args.sequence, "frames": n,
                   "poses": len(traj), "estimate": str(est_path), "overlay": str(overlay) if overlay else None,
                   "plots": str(plots), "endpoint": endpoint, "published": published["n"],
                   "local_fallback": fallback is not None, "method": "render-match over zenoh + local P&L",
                   "odometry": args.odometry, **s,
                   **{f"{k}_s": round(v, 1) for k, v in clock.wall.items()}, "total_s": round(wall, 1),
                   "cpu_s": round(cpu, 1)}
        for name, r in results.items():
            summary[f"ape_{name}_trans_rmse_m"] = r.trans_rmse
            summary[f"ape_{name}_rot_rmse_deg"] = r.rot_rmse_deg
        summary["fraction"] = results["none"].fraction if results else 0.0
        if srv_ape is not None:
            summary["ape_none_server_trans_rmse_m"] = srv_ape.trans_rmse
            summary["ape_none_server_rot_rmse_deg"] = srv_ape.rot_rmse_deg
        if args.keep_server:
            print(f"router and server keep running on {endpoint} (Ctrl-C stops them); try:\n"
                  f"  cristal stream {seq_dir} --out /tmp/stream.txt --map /tmp/pnl-cache --connect {endpoint}", flush=True)
            stop.wait_for_interrupt()
            summary["served_after"] = dict(server.counts)
    emit_summary(summary)
    return 0 if len(traj) else 1
