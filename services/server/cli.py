"""``cristal router`` (a Zenoh router in-process) and ``cristal serve`` (the localization server)."""

from __future__ import annotations

import argparse

from services.localize.cli import add_gate_arguments, resolve_scan_sigma, rm_gates

ROUTER_EPILOG = """\
examples:
  cristal router                                       listen on tcp/127.0.0.1:7447 (servers and clients connect here)
  cristal router --listen tcp/0.0.0.0:7447             accept the whole network
  cristal router --zenoh-config deploy/zenoh/router-acl.json5

The zenoh Python binding runs the router itself (mode "router"), so no separate binary is needed.
In production you may run eclipse-zenoh's own 'zenohd -c deploy/zenoh/router.json5' instead:
same configuration files, same protocol. Stops on Ctrl-C / SIGTERM.
"""

SERVE_EPILOG = """\
examples:
  cristal serve site/scan.ply --db site/reloc.npz --map site/pnl          listen on tcp/127.0.0.1:7447 (no router needed)
  cristal serve scan.ply --db reloc.npz --connect tcp/10.0.0.2:7447 --site hq --map-id floor2 --server-id gpu0
  cristal serve scan.ply --db reloc.npz --zenoh-config deploy/zenoh/server-tls.json5 --metrics-port 9464

Several servers may serve the same --site/--map-id: connect them all to one router
('cristal router' or zenohd) and clients spread over them and fail over between them.
Key expressions: see protocol/keys.py and the README's Service section.
"""


def backend_configs(args) -> tuple:
    """(RMConfig, PnlConfig) of ``cristal serve``'s report gates: each client's tracker meets them (the backend's)."""
    from services.localize.pnl_cli import pnl_config

    if args.backend == "rm":
        from services.localize.render_match import RMConfig

        return RMConfig(**rm_gates(args)), None
    return None, pnl_config(args)


def _zenoh_args(p, role: str) -> None:
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 configuration (deploy/zenoh/ has examples)")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="listen endpoint (repeatable)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="connect endpoint, e.g. a router (repeatable)")


def register(sub) -> None:
    r = sub.add_parser("router", help="run a Zenoh router (servers and clients meet there)",
                       description="Run a Zenoh router in this process.", epilog=ROUTER_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _zenoh_args(r, "router")
    r.add_argument("--duration", type=float, help="stop after this many seconds (default: run until interrupted)")
    r.set_defaults(func=run_router)

    s = sub.add_parser("serve", help="serve localization over Zenoh (Render & Match per client)",
                       description="The localization server: frames in, camera-to-world poses out, over Zenoh.",
                       epilog=SERVE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("scan", nargs="?", help="the scan (PLY/E57/LAS/LAZ); needed by the rm backend")
    s.add_argument("--db", help="relocalization database from 'cristal build-db' (rm backend)")
    s.add_argument("--map", dest="map_dir", metavar="MAPDIR", help="P&L map directory (map.msg + config.yaml): served to clients")
    s.add_argument("--backend", choices=["rm", "pnl"], default="rm", help="rm: Render & Match (default); pnl: the light P&L "
                   "localizer on this CPU (needs only --map)")
    s.add_argument("--site", default="default", help="site id (key scope, default 'default')")
    s.add_argument("--map-id", default="default", help="map id (key scope, default 'default')")
    s.add_argument("--server-id", default="", help="this worker's id (default: random)")
    s.add_argument("--workers", type=int, default=1, help="frames processed in parallel (default 1)")
    s.add_argument("--max-clients", type=int, default=64,
                   help="clients tracked at once; one more is answered with a reason, not served (default 64)")
    s.add_argument("--idle", type=float, default=60.0, help="seconds before an idle client's state expires (default 60)")
    s.add_argument("--evict-after", type=float, default=5.0, metavar="S",
                   help="when --max-clients are held, a new client takes the place of the one silent longest if it has "
                        "been silent S seconds (default 5; 0: refuse newcomers until a state expires)")
    s.add_argument("--metrics-port", type=int, default=0, help="Prometheus exporter port (default 0: off; 9464 is usual)")
    s.add_argument("--metrics-addr", default="127.0.0.1",
                   help="address the Prometheus exporter listens on (default 127.0.0.1; 0.0.0.0 for a scraper on another host)")
    s.add_argument("--device", default="auto", help="cpu, cuda or auto (default: cuda when available)")
    add_gate_arguments(s)
    s.add_argument("--duration", type=float, help="stop after this many seconds (default: run until interrupted)")
    _zenoh_args(s, "server")
    s.set_defaults(func=run_serve)


def _wait(duration: float | None) -> None:
    import signal
    import threading

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait(duration)


def run_router(args) -> int:
    import logging

    from services.cli import emit_summary
    from services.zconfig import make_config, open_session

    cfg = make_config(args.zenoh_config, mode="router", listen=args.listen, connect=args.connect, default_role="server")
    s = open_session(cfg)
    try:
        logging.getLogger("cristal").info("zenoh router %s listening on %s", s.zid(), cfg.get_json("listen/endpoints"))
        print(f"router {s.zid()} listening on {cfg.get_json('listen/endpoints')}", flush=True)
        _wait(args.duration)
    finally:
        s.close()
    emit_summary({"router": str(s.zid())})
    return 0


def run_serve(args) -> int:
    import os

    from services.cli import CliError, emit_summary
    from services.server.backend import load_backend
    from services.server.service import LocalizationServer, ServerConfig
    from services.zconfig import make_config

    if args.backend == "rm":
        if not args.scan or not args.db:
            raise CliError("the rm backend needs SCAN and --db (or use --backend pnl --map MAPDIR)")
        import torch

        torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
        if args.scan_sigma_mm == "auto":  # what build-db recorded, else measured from the scan (loaded once more)
            from services.io.scans import load_scan
            from services.relocalize.database import RelocDB

            meta = RelocDB.load_meta(args.db)
            resolve_scan_sigma(args, None if "scan_sigma_mm" in meta else load_scan(args.scan), meta)
    elif args.map_dir:
        resolve_scan_sigma(args, map_dir=args.map_dir)
    cfg = ServerConfig(site=args.site, map_id=args.map_id, server_id=args.server_id, workers=args.workers,
                       max_clients=args.max_clients, idle_s=args.idle, evict_silent_s=args.evict_after,
                       metrics_port=args.metrics_port, metrics_addr=args.metrics_addr)
    zc = make_config(args.zenoh_config, listen=args.listen, connect=args.connect, default_role="server")
    backend = load_backend(args.backend, args.scan, args.db, args.map_dir, args.device, *backend_configs(args))
    srv = LocalizationServer(backend, cfg, zc, bundle_dir=args.map_dir)
    srv.start()
    try:
        print(f"serving site {cfg.site!r} map {cfg.map_id!r} as {cfg.server_id} ({backend.name}); "
              f"zenoh listen={zc.get_json('listen/endpoints')} connect={zc.get_json('connect/endpoints')}", flush=True)
        _wait(args.duration)
    finally:
        srv.close()
    emit_summary({"server": cfg.server_id, **srv.counts})
    return 0
