"""``cristal``: one command, one subcommand per job. Every subcommand is a thin layer over a library function.

Subcommand modules only import argparse at the top so that ``cristal --help`` is instant;
each provides ``register(subparsers)`` and does its heavy imports inside its handler.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys

from services.log import setup_logging

# (module, one-line purpose) in the order --help lists them.
COMMANDS = [
    "services.demo",
    "services.sim.cli",
    "services.io.cli",
    "services.eval.cli",
    "services.render.cli",
    "services.localize.cli",
    "services.prebuild.cli",
    "services.server.cli",
    "services.client.cli",
]

EPILOG = """\
typical session:
  cristal demo --out runs/demo                 the whole loop: simulate, build, serve + stream over Zenoh, score
  cristal sim --preset office --seed 1 --out site/   a simulated scene: scan.ply + camera sequences with ground truth
  cristal scan info site/scan.ply              points, bounds, origin, colours, load time
  cristal eval site/seq_0/groundtruth.txt est.txt   APE (no alignment and SE(3)), plots

Conventions: poses are camera-to-world in the scan's metric frame, TUM files are
'timestamp tx ty tz qx qy qz qw'. See docs/ and README.md.
"""


class CliError(Exception):
    """An error the user can act on: printed as one line, exit code 2."""


def near_arg(values: list[float] | None) -> tuple[tuple[float, float, float], float] | None:
    """``--near X Y Z R`` as ((x, y, z), radius m), or None when not given; a CliError unless all are finite, R > 0."""
    if values is None:
        return None
    import math

    if not (all(map(math.isfinite, values)) and values[3] > 0):
        raise CliError(f"--near X Y Z R: a world position and a radius > 0 in metres (got {values})")
    return (values[0], values[1], values[2]), values[3]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cristal",
        description="Real-time camera registration in static LiDAR scans.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    p.add_argument("-j", "--threads", type=int, metavar="N",
                   help="CPU threads for numba, torch and OpenCV (default: all cores; on a busy box fewer can be faster)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for mod in COMMANDS:
        importlib.import_module(mod).register(sub)
    return p


def parse_pose(text: str, option: str = "--pose"):
    """A camera-to-world pose from the command line: 'tx ty tz qx qy qz qw' (commas allowed)."""
    from services.geometry.se3 import Pose

    try:
        return Pose.from_tum([float(x) for x in text.replace(",", " ").split()])
    except ValueError as e:
        raise CliError(f"{option}: {e} (expected 'tx ty tz qx qy qz qw')") from None


def add_odometry_args(p: argparse.ArgumentParser, use: str) -> None:
    """``--odometry`` and ``--odometry-axes`` (localize, stream): ``use`` says what the command does with it."""
    p.add_argument("--odometry", metavar="TUM",
                   help="the device's own odometry (VIO, wheels): a TUM trajectory in any frame of its own, on the frames' "
                        "clock, logged at any rate (interpolated at each frame); " + use)
    p.add_argument("--odometry-axes", choices=["opencv", "opengl"], default="opencv",
                   help="the camera axes of the odometry's poses: opencv (x right, y down, z forward; the default, as "
                        "every pose here) or opengl (x right, y up, z backward: ARKit, ARCore, game engines)")


def roi_polygon(vertices: list[str]) -> tuple[tuple[float, float], ...]:
    """``--roi-polygon X,Y ...`` (build-db, prebuild) as vertices; a clear error for anything else."""
    try:
        return tuple((float(v.split(",")[0]), float(v.split(",")[1])) for v in vertices)
    except (ValueError, IndexError):
        raise CliError(f"--roi-polygon: expected vertices as X,Y (e.g. 0,0 12,0 12,5 0,5), got {' '.join(vertices)}") from None


def positions_picture(positions, out, **kw):
    """OUT.png beside a database (or MAPDIR/map.png): where it was rendered from, over the scan or the map's
    landmarks; None (logged) when it cannot be drawn: the database or map is written either way."""
    from services.eval.plots import drawn, picture_path, plot_positions_topdown

    path = drawn("the positions", plot_positions_topdown, positions, picture_path(out), **kw)
    if path is not None:
        print(f"picture: {path} (the region of interest seen from above: are these where cameras go?)")
    return path


def emit_summary(summary: dict) -> None:
    """The last line of every job's stdout: one JSON object, machine-readable."""
    print(json.dumps(summary, sort_keys=True, default=float), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(-1 if args.quiet else args.verbose)
    # OpenMP threads (numba's and torch's) must not spin-wait after a parallel region: on a 2-core box a
    # spinning numba pool steals the core torch needs next (measured: XFeat 61 -> 46 ms per frame).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if args.threads:
        # read by numba and torch when they are first imported (handlers import them lazily)
        for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.threads)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        rc = args.func(args)
        return int(rc or 0)
    except KeyboardInterrupt:
        logging.getLogger("cristal").error("interrupted")
        return 130
    except (CliError, ValueError, FileNotFoundError, OSError) as e:
        # Errors of our own readers are ValueError subclasses that already name the file and the problem.
        logging.getLogger("cristal").error("%s", e)
        if args.verbose > 1:
            raise
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
