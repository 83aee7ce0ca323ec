"""``cristal scan info`` (what is in a scan file), ``cristal scan check`` (how well its stations agree) and
``cristal scan convert`` (to PLY, optionally thinned)."""

from __future__ import annotations

import argparse

EPILOG = """\
examples:
  cristal scan info site/scan.ply                  points, world bounds, origin, colours, stations, load time
  cristal scan info survey.e57 --no-cache          parse the file even if a cache exists (and do not write one)
  cristal scan convert survey.e57 scan.ply         all E57 scans merged into one PLY in the world frame
  cristal scan convert big.laz small.ply --voxel 0.02    one point per 2 cm voxel (colour = voxel mean)
  cristal scan convert big.ply half.ply --fraction 0.5   a random half (same --seed, same half)
  cristal scan convert raw.e57 scan.ply --drop-floating  without the points that lie on no surface (mixed pixels)
  cristal scan check survey.e57 --plot check.png   how well the stations agree: the registration error, in mm

formats: .ply (binary or ASCII; uchar, ushort or float colours), .e57 (every scan, moved by its pose
into the file's world frame), .las/.laz (16-bit colours scaled to 8 bit). Points with NaN/inf
coordinates are dropped and counted. The first load writes '<file>.cristal-cache/' (or
~/.cache/cristal/ when the scan's folder is read-only); later loads map it in milliseconds
and re-parse by themselves when the file changes.
"""

INFO_EPILOG = """\
example:
  cristal scan info site/scan.ply
  cristal scan info survey.e57 --no-cache --allow-no-color

The last stdout line is a JSON summary (points, bounds_min/max, origin, stations, from_cache, ...).
"""

CHECK_EPILOG = """\
examples:
  cristal scan check survey.e57
  cristal scan check site/scan.ply --sample 50000 --plot check.png

Where two stations saw the same surface their points should lie on it together. For a sample of each station's
points on flat surfaces this measures the distance to the other station's local plane and to its own (the range
noise, which the first holds too): the registration's share is what is left. The result is what a registration
report's cloud-to-cloud error says. 'cristal build-db' and 'prebuild' measure it too and record it with the database
and the map; 'cristal localize / serve / stream' count it in each pose's reported 1-sigma (--scan-sigma-mm, default
auto): no camera is placed better than its scan, and its 1-sigma then says so.
A camera between stations that disagree by s errs up to about 2 s at its centre and s / d in orientation (d: the
distance to what it sees): 8 mm at 2 m is 1.6 cm / 0.23 deg, beyond the 1 cm / 0.1 deg a perfect scan allows.

A pair's disagreement is both stations' errors; solved over all pairs, each station's own share is printed and a
station far beyond the rest is named loose (a setup few targets held: re-register it; --plot rings it). With three or
more stations that share surfaces; two alone split it. The record keeps where on the site the error lies, and each
pose counts the disagreement of the stations whose points it sees, not the pooled number.

Needs to know which points each station has: E57 files (one scan per station), simulated scans and PLY files
written by cristal ('cristal scan convert survey.e57 scan.ply' keeps it). A merged PLY from elsewhere cannot tell.
The last stdout line is a JSON summary (registration_mm, noise_mm, pairs, station_mm, loose_stations).
"""

CONVERT_EPILOG = """\
examples:
  cristal scan convert survey.e57 scan.ply                 merge all scans, binary PLY
  cristal scan convert scan.laz scan.ply --voxel 0.01      1 cm voxel grid: nearest-to-mean point, mean colour
  cristal scan convert scan.ply preview.ply --fraction 0.05 --ascii   5 % random subset as ASCII PLY
  cristal scan convert raw.e57 scan.ply --drop-floating    drop mixed pixels, dust, passers-by's stray returns

--drop-floating: a point with fewer than 3 others within 5 ray spacings (the scanner's angular step, read from the
scan, at the distance to the nearest station) lies on no surface: a beam that straddled a silhouette came back from
between the two surfaces (a mixed pixel). Such points paint over the surface behind them in every render, and the
depth filter then takes them for foreground; on a simulated office with 30 % of its edge returns mixed, dropping them
took Render & Match from 270 to 278 of 300 frames and 0.34 to 0.20 cm. Usually 0.1-0.5 % of a scan; a warning says
when far more would go (surfaces seen only from far stations). Runs before --voxel / --fraction.

Coordinates are written in the world frame: double when the scan needed an origin (large survey
coordinates), float otherwise. Scanner stations are kept as 'comment cristal_station' header lines, and which
points each station has ('cristal scan check' needs it) as 'comment cristal_station_points'; --voxel loses that
(a voxel's point stands for every station's), --fraction and --drop-floating keep it.
"""


def register(sub) -> None:
    p = sub.add_parser("scan", help="inspect or convert a LiDAR scan (.ply, .e57, .las, .laz)",
                       description="Inspect or convert a LiDAR scan.", epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ss = p.add_subparsers(dest="scan_command", metavar="ACTION", required=True)

    i = ss.add_parser("info", help="points, bounds, origin, colours, stations, load time",
                      description="Load a scan and describe it.", epilog=INFO_EPILOG,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    i.add_argument("scan", metavar="SCAN", help="scan file (.ply, .e57, .las, .laz)")
    i.add_argument("--no-cache", action="store_true", help="parse the file; neither read nor write the cache")
    i.add_argument("--allow-no-color", action="store_true", help="accept a scan with neither colour nor intensity "
                   "(flat grey points)")
    i.set_defaults(func=run_info)

    k = ss.add_parser("check", help="how well the scan's stations agree: its registration error (mm)",
                      description="Measure how well a scan's stations agree (its registration error).",
                      epilog=CHECK_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    k.add_argument("scan", metavar="SCAN", help="scan file (.ply, .e57, .las, .laz) that knows its stations' points")
    k.add_argument("--sample", type=int, default=20_000, metavar="N", help="points sampled per station (default 20000)")
    k.add_argument("--plot", metavar="OUT.png", help="also draw the stations from above, each pair that shares "
                                                        "surfaces joined in the colour of its disagreement")
    k.add_argument("--allow-no-color", action="store_true", help="accept a scan with neither colour nor intensity "
                   "(flat grey points)")
    k.set_defaults(func=run_check)

    c = ss.add_parser("convert", help="convert to PLY, optionally voxel- or randomly thinned",
                      description="Convert a scan to PLY (world frame, uchar colours).", epilog=CONVERT_EPILOG,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("input", metavar="IN", help="scan file (.ply, .e57, .las, .laz)")
    c.add_argument("output", metavar="OUT.ply", help="PLY file to write (atomically)")
    thin = c.add_mutually_exclusive_group()
    thin.add_argument("--voxel", type=float, metavar="M", help="keep one point per voxel of M metres")
    thin.add_argument("--fraction", type=float, metavar="F", help="keep a random fraction F in (0, 1] of the points")
    c.add_argument("--drop-floating", action="store_true",
                   help="drop points that lie on no surface: mixed pixels along silhouettes, dust (see below)")
    c.add_argument("--seed", type=int, default=0, help="random seed for --fraction (default 0)")
    c.add_argument("--ascii", action="store_true", help="write ASCII PLY (large; for inspection)")
    c.add_argument("--no-cache", action="store_true", help="parse the input; neither read nor write its cache")
    c.add_argument("--allow-no-color", action="store_true", help="accept an input with neither colour nor intensity "
                   "(flat grey points)")
    c.set_defaults(func=run_convert)


def run_info(args) -> int:
    from services.cli import emit_summary
    from services.io.scan import level_warning
    from services.io.scans import load_scan, scan_info, station_points

    scan = load_scan(args.scan, cache=not args.no_cache, require_color=not args.allow_no_color)
    s = scan_info(scan)
    lo, hi = s["bounds_min"], s["bounds_max"]
    print(f"{args.scan}: {s['points']:,} points ({s['format']}), "
          f"loaded in {s['load_seconds']:.2f} s {'from the cache' if s['from_cache'] else 'by parsing the file'}")
    print(f"  bounds (world): x {lo[0]:.3f} .. {hi[0]:.3f}, y {lo[1]:.3f} .. {hi[1]:.3f}, z {lo[2]:.3f} .. {hi[2]:.3f} "
          f"(extent {hi[0] - lo[0]:.2f} x {hi[1] - lo[1]:.2f} x {hi[2] - lo[2]:.2f} m)")
    print(f"  origin: {' '.join(f'{v:.3f}' for v in s['origin'])}"
          + (" (coordinates stored relative to it)" if any(s["origin"]) else ""))
    grey = s["intensity_grey"]
    print(f"  colour: {'yes' if s['has_color'] else 'no'}"
          + (f"; {grey:,} points grey from the laser's intensity" if grey else
             "" if s["has_color"] else " (flat grey)"))
    why = level_warning(scan)
    known = station_points(scan) is not None
    print(f"  stations: {len(s['stations'])}" + (", upright (z up)" if scan.stations and not why else "")
          + (", each one's points known ('cristal scan check' measures how well they agree)" if known else ""))
    if why:
        print(f"  WARNING: {why}")
    for k, st in enumerate(s["stations"]):
        print(f"    {k}: t = {st[0]:.3f} {st[1]:.3f} {st[2]:.3f}, q_xyzw = {st[3]:.4f} {st[4]:.4f} {st[5]:.4f} {st[6]:.4f}")
    print(f"  dropped: {s['dropped_nonfinite']} non-finite, {s['dropped_invalid']} flagged invalid")
    s["upright"] = (why is None) if scan.stations else None  # None: no stations to tell
    s["station_points_known"] = known
    emit_summary(s)
    return 0


def run_check(args) -> int:
    import numpy as np

    from services.cli import CliError, emit_summary
    from services.io.registration import station_agreement
    from services.io.scans import load_scan
    from services.localize.scan_error import scan_floor

    if args.sample < 100:
        raise CliError(f"--sample must be at least 100 points per station, got {args.sample}")
    scan = load_scan(args.scan, require_color=not args.allow_no_color)
    a = station_agreement(scan, sample=args.sample)
    summary = {"scan": str(args.scan), "stations": len(scan.stations), "registration_mm": None, "noise_mm": None,
               "pairs": []}
    if a is None:
        why = ("it has one station" if len(scan.stations) == 1 else
               "it does not say which points each station has (a merged PLY from elsewhere; E57 files, simulated "
               "scans and PLY written by 'cristal scan convert' do)")
        print(f"{args.scan}: cannot tell how well its stations agree: {why}")
    elif not a.pairs:
        print(f"{args.scan}: {a.stations} stations, but no two share enough of a flat surface to compare")
    else:
        mm = 1e3 * a.registration_m
        summary.update(registration_mm=round(mm, 2), noise_mm=round(1e3 * a.noise_m, 2), pairs=[
            {"a": p.a, "b": p.b, "shared": p.n, "between_mm": round(1e3 * p.between_m, 2),
             "registration_mm": round(1e3 * p.registration_m, 2)} for p in a.pairs])
        print(f"{args.scan}: {a.stations} stations, {len(a.pairs)} pairs sharing flat surfaces; range noise "
              f"{1e3 * a.noise_m:.1f} mm")
        print(f"  registration error (the stations' disagreement beyond the noise): {mm:.1f} mm")
        print("  station  against  shared points  distance mm  registration mm")
        for p in sorted(a.pairs, key=lambda p: -p.registration_m):
            print(f"  {p.a:7d}  {p.b:7d}  {p.n:13,d}  {1e3 * p.between_m:11.1f}  {1e3 * p.registration_m:15.1f}")
        own_m = a.station_sigmas_m()
        sig = 1e3 * own_m
        summary["station_mm"] = [None if not np.isfinite(x) else round(float(x), 2) for x in sig]
        print(f"  each station's own share (from all its pairs; the worst {min(10, len(sig))} of {len(sig)}):")
        print("  station  registration mm")
        for k in np.argsort(-np.nan_to_num(sig, nan=-1.0))[:10]:
            print(f"  {k:7d}  {sig[k]:15.1f}" if np.isfinite(sig[k]) else f"  {k:7d}  {'(no shared surface)':>15s}")
        loose = a.loose_stations(own_m)
        summary["loose_stations"] = loose
        if loose:
            who = (f"stations {', '.join(map(str, loose))} disagree with their" if len(loose) > 1 else
                   f"station {loose[0]} disagrees with its")
            print(f"  {who} neighbours well beyond the rest: check the registration there (targets, overlap)")
        floor_m, floor_deg = scan_floor(mm / 1000, 2.0)
        print(f"  a camera placed in it errs up to {100 * floor_m:.1f} cm and {floor_deg:.2f} deg seen at 2 m: "
              "'cristal build-db' and 'prebuild' record it, and each pose's reported 1-sigma counts it ("
              f"--scan-sigma-mm auto; or pass {mm:.1f})" + ("; over 1 cm: check the registration" if mm > 10 else ""))
        if args.plot:
            from services.eval.plots import drawn, plot_station_agreement

            path = drawn("the stations", plot_station_agreement, a, scan, args.plot)
            summary["picture"] = path and str(path)
            if path is not None:
                print(f"picture: {path} (the stations from above; each pair joined in the colour of its disagreement)")
    emit_summary(summary)
    return 0


def run_convert(args) -> int:
    import time
    from pathlib import Path

    from services.cli import emit_summary
    from services.io.decimate import random_decimate, voxel_decimate
    from services.io.scan import ScanError
    from services.io.scans import load_scan, save_ply

    out = Path(args.output)
    if out.suffix.lower() != ".ply":
        raise ScanError(f"{out}: the output must be a .ply file")
    t0 = time.perf_counter()
    scan = load_scan(args.input, cache=not args.no_cache, require_color=not args.allow_no_color)
    n_in = len(scan)
    floating = None
    if args.drop_floating:
        from services.io.floating import drop_floating

        scan = drop_floating(scan)
        floating = scan.meta["floating_dropped"]
        print(f"floating points dropped: {floating:,} ({100.0 * floating / max(n_in, 1):.2f} %)")
    if args.voxel is not None:
        scan = voxel_decimate(scan, args.voxel)
    elif args.fraction is not None:
        scan = random_decimate(scan, args.fraction, seed=args.seed)
    save_ply(scan, out, binary=not args.ascii)
    dt = time.perf_counter() - t0
    print(f"{args.input} -> {out}: {n_in:,} -> {len(scan):,} points, {len(scan.stations)} stations, {dt:.1f} s")
    emit_summary({"input": str(args.input), "output": str(out), "points_in": n_in, "points_out": len(scan),
                  "stations": len(scan.stations), "floating_dropped": floating, "seconds": round(dt, 3)})
    return 0
