"""``cristal eval``: APE of an estimated TUM trajectory against ground truth, with plots."""

from __future__ import annotations

import argparse

EPILOG = """\
examples:
  cristal eval site/seq_00/groundtruth.txt est.txt                 APE with no alignment, SE(3) and Sim(3)
  cristal eval gt.txt est.txt --align none                         only in the scan frame (what the product claims)
  cristal eval gt.txt est.txt --plots plots/ --scan site/scan.ply  + trajectory.png (over the scan), errors_<align>.png
  cristal eval gt.txt est.txt --json ape.json                      + full results per alignment as JSON

Uncertainty: `cristal localize --out est.txt` also writes est.frames.csv (every frame's status,
inliers and predicted 1-sigma). When it is there (or given with --frame-log), eval also counts the
poses whose error exceeds 3 times the 1-sigma they were reported with (in the scan frame, no
alignment), and with --plots draws uncertainty.png: error against predicted 1-sigma. It also
breaks the error down by what solved each pose (the log's source column: "features", matched
keypoints; "direct", image patches aligned to the render or map; "fused", both), which usually
tells where a walk's error sits.

Frames are matched by their exact timestamp text; an estimated timestamp missing from the
ground truth is an error (use --lenient to ignore such frames). 'fraction' is the share of
ground-truth frames that got a pose. Numbers equal evo_ape's (translation_part and
rotation_angle_deg) on the same files. The last stdout line is a one-line JSON summary.
"""


def register(sub) -> None:
    p = sub.add_parser("eval", help="APE of a trajectory against ground truth (none / SE(3) / Sim(3)), plots",
                       description="APE (absolute pose error) of an estimated TUM trajectory against ground truth: "
                                   "translation and rotation errors after no, SE(3) or Sim(3) alignment; plots.",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("gt", help="ground-truth TUM file (camera-to-world)")
    p.add_argument("est", help="estimated TUM file (camera-to-world)")
    p.add_argument("--align", choices=["none", "se3", "sim3", "all"], default="all",
                   help="alignment of the estimate before scoring (default: all = none, se3 and sim3)")
    p.add_argument("--scan", help="scan file drawn under the top-view plot (needs --plots)")
    p.add_argument("--plots", metavar="DIR", help="write trajectory.png and errors_<align>.png here")
    p.add_argument("--json", metavar="FILE", help="write the results (summary per alignment) as JSON")
    p.add_argument("--lenient", action="store_true", help="ignore estimated frames whose timestamp is not in the ground truth")
    p.add_argument("--frame-log", metavar="CSV", help="per-frame log with each pose's predicted 1-sigma (default: "
                                                       "EST.frames.csv beside the estimate, when there)")
    p.set_defaults(func=run)


def _table(results) -> None:
    from rich import box
    from rich.console import Console
    from rich.table import Table

    t = Table(box=box.SIMPLE_HEAD, pad_edge=False, title="APE (absolute pose error)", caption=f"sim3 scale {results['sim3'].scale:.5f}" if "sim3" in results else None)
    t.add_column("alignment")
    for col in ("frames", "fraction", "trans RMSE cm", "trans median cm", "rot RMSE deg", "rot median deg"):
        t.add_column(col, justify="right")
    for name, r in results.items():
        t.add_row(name, f"{r.n_matched}/{r.n_gt}", f"{r.fraction:.3f}", f"{100 * r.trans_rmse:.2f}",
                  f"{100 * r.trans_median:.2f}", f"{r.rot_rmse_deg:.3f}", f"{r.rot_median_deg:.3f}")
    console = Console()
    if not console.is_terminal:  # a pipe or log file: no reason to wrap the headers at 80 columns
        console.width = max(console.width, 100)
    console.print(t)


def _frame_log(args) -> tuple[str, dict] | None:
    """(path, stamp -> FrameRecord) of the frame log (--frame-log, else EST.frames.csv when it exists), or None."""
    from services.cli import CliError
    from services.io.frame_log import FrameLogError, frame_log_path, read_frame_log

    path = args.frame_log or frame_log_path(args.est)
    if args.frame_log is None and not path.is_file():
        return None
    try:
        return str(path), read_frame_log(path)
    except FrameLogError as e:
        raise CliError(str(e)) from None


def _uncertainty(args, gt, est, results, path: str, records: dict) -> dict:
    """services.eval.ape.uncertainty_check against the frame log ``records`` (read from ``path``). Prints a line."""
    from services.eval.ape import compute_ape, errors_by_source, uncertainty_check

    none = results.get("none") or compute_ape(gt, est, "none", strict=not args.lenient)
    c = uncertainty_check(none, records)
    c["by_source"] = by = errors_by_source(none, records)
    if len(by) > 1 or "" not in by:
        print("error by what solved the pose (no alignment): " + "; ".join(
            f"{src or 'not logged'} {g['n']} poses, {100 * g['trans_rmse_m']:.2f} cm / {g['rot_rmse_deg']:.3f} deg RMSE "
            f"(worst {100 * g['trans_max_m']:.2f} cm / {g['rot_max_deg']:.2f} deg)" for src, g in by.items()))
    if c["n"]:
        print(f"predicted uncertainty ({path}): {c['n']} poses with a 1-sigma; error / 1-sigma median "
              f"{c['t_ratio_median']:.2f} (centre), {c['r_ratio_median']:.2f} (orientation); "
              f"{c['beyond_3sigma']} beyond 3 sigma ({100 * c['beyond_3sigma'] / c['n']:.1f} %)")
    else:
        print(f"predicted uncertainty ({path}): no pose with a 1-sigma")
    return c


def run(args) -> int:
    import json
    from pathlib import Path

    from services.cli import CliError, emit_summary
    from services.eval.ape import ALIGNMENTS, evaluate
    from services.io.atomic import atomic_write_text
    from services.io.trajectory import read_tum

    if args.scan and not args.plots:
        raise CliError("--scan is only used for plots: add --plots DIR")
    gt, est = read_tum(args.gt), read_tum(args.est)
    if len(gt) == 0:
        raise CliError(f"{args.gt}: the ground truth has no poses")
    aligns = ALIGNMENTS if args.align == "all" else (args.align,)
    results = evaluate(gt, est, aligns, strict=not args.lenient)
    if not results:
        raise CliError(f"no alignment possible ({args.align}): too few or collinear matched frames")
    _table(results)

    first = next(iter(results.values()))
    summary = {"gt": str(args.gt), "est": str(args.est), "n_gt": first.n_gt, "n_est": first.n_est,
               "n_matched": first.n_matched, "fraction": first.fraction, "aligns": list(results)}
    for name, r in results.items():
        for k in ("trans_rmse", "trans_mean", "trans_median", "trans_max"):
            summary[f"ape_{name}_{k}_m"] = getattr(r, k)
        for k in ("rot_rmse_deg", "rot_mean_deg", "rot_median_deg", "rot_max_deg"):
            summary[f"ape_{name}_{k}"] = getattr(r, k)
        if name == "sim3":
            summary["ape_sim3_scale"] = r.scale

    frame_log = _frame_log(args)
    check = None if frame_log is None else _uncertainty(args, gt, est, results, *frame_log)
    if check is not None:
        summary.update({f"uncertainty_{k}": check[k] for k in ("n", "beyond_3sigma", "t_ratio_median", "r_ratio_median")})
        summary["by_source"] = check["by_source"]
    if args.plots:
        from services.eval.plots import plot_errors, plot_trajectory_topdown, plot_uncertainty

        scan = None
        if args.scan:
            from services.io.scans import load_scan

            scan = load_scan(args.scan, require_color=False)  # grey points are fine for a plot
        out = Path(args.plots)
        files = [plot_trajectory_topdown(gt, est, out / "trajectory.png", scan=scan, frame_log=frame_log and frame_log[1],
                                         title=f"{Path(args.est).name} vs {Path(args.gt).name} (top view)")]
        files += [plot_errors(r, out / f"errors_{name}.png") for name, r in results.items()]
        if check is not None and check["n"]:
            files.append(plot_uncertainty(check, out / "uncertainty.png"))
        print("plots: " + ", ".join(str(f) for f in files))
        summary["plots"] = [str(f) for f in files]
    if args.json:
        doc = {name: {**r.summary(), "alignment_tum": [float(v) for v in r.alignment.to_tum()]}
               for name, r in results.items()}
        atomic_write_text(args.json, json.dumps(doc, indent=2, sort_keys=True) + "\n")
        summary["json"] = str(args.json)
    emit_summary(summary)
    return 0
