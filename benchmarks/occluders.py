"""People in front of the camera: a walk copied with passers-by pasted over it, localized by both methods.

    python benchmarks/occluders.py [--site runs/bench-sim/office] [--texture-site runs/bench-sim/warehouse]
                                   [--cover 0.2 0.4] [--seed 1] [--out runs/occluders]

The scan is static; the world in front of a headset or a robot is not. For each --cover (the share of the frame's
width two passers-by take together), SITE/seq_00 is copied into OUT/cover-X/ with two person-shaped occluders
(a head and a body, 0.9 of the frame high) walking across it at 3-8 px a frame and turning at the edges, textured
with crops of another site's frames (--texture-site: real structure, which is what takes a feature detector's
strongest keypoints; random noise does not). Ground truth is copied. Then `cristal localize` runs Render & Match
(SITE/reloc.npz) and Prebuild & Localize (SITE/map) over the copy and the original, each from a cold start, and
a table prints frames localized, APE with no alignment and FPS. OUT/cover-X/example.png shows the last frame.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from services.io.sequence import SequenceWriter, open_sequence  # noqa: E402


def occlude(src: Path, textures: Path, out: Path, cover: float, seed: int) -> float:
    """Writes the occluded copy of sequence ``src`` to ``out``; returns the mean share of pixels covered."""
    seq, tex_seq = open_sequence(src), open_sequence(textures)
    rng = np.random.default_rng(seed)
    H, W = seq.camera.height, seq.camera.width
    w, h = max(8, int(cover * W / 2)), int(0.9 * H)
    people = []
    for _ in range(2):
        img = cv2.resize(tex_seq.read(int(rng.integers(len(tex_seq)))).image, (max(W, w), max(H, h)))
        y0, x0 = int(rng.integers(0, img.shape[0] - h + 1)), int(rng.integers(0, img.shape[1] - w + 1))
        people.append({"tex": img[y0:y0 + h, x0:x0 + w], "x": float(rng.uniform(0, W - w)),
                       "v": float(rng.choice([-1, 1]) * rng.uniform(3, 8))})
    shape = np.zeros((h, w), np.uint8)
    cv2.circle(shape, (w // 2, w // 3), w // 3, 255, -1)  # head
    cv2.rectangle(shape, (0, int(0.6 * w)), (w - 1, h - 1), 255, -1)  # body
    covered = []
    with SequenceWriter(out, seq.camera) as writer:
        for i in range(len(seq)):
            f = seq.read(i)
            img, cov = f.image.copy(), np.zeros((H, W), bool)
            for p in people:
                p["x"] += p["v"]
                if not -0.5 * w <= p["x"] <= W - 0.5 * w:
                    p["v"] = -p["v"]
                x = int(p["x"])
                a, b = max(0, x), min(W, x + w)
                if b <= a:
                    continue
                m = shape[:, a - x:b - x] > 0
                img[H - h:, a:b][m] = p["tex"][:, a - x:b - x][m]
                cov[H - h:, a:b] |= m
            covered.append(cov.mean())
            writer.add(seq.stamps[i], img, seq.groundtruth_pose(f.stamp) if seq.groundtruth is not None else None)
    cv2.imwrite(str(out / "example.png"), img)
    return float(np.mean(covered))


def localize(site: Path, seq: Path, method: str, out: Path) -> dict:
    src = site / "scan.ply" if method == "rm" else site / "map"
    extra = ["--db", str(site / "reloc.npz"), "--no-camera-check"] if method == "rm" else ["--map", str(site / "map")]
    cmd = ["cristal", "-q", "localize", str(src), str(seq), "--method", method, "--out", str(out), *extra]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", type=Path, default=Path("runs/bench-sim/office"))
    ap.add_argument("--texture-site", type=Path, default=Path("runs/bench-sim/warehouse"))
    ap.add_argument("--cover", type=float, nargs="+", default=[0.2, 0.4])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("runs/occluders"))
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    runs = [("none", 0.0, args.site / "seq_00")]
    for c in args.cover:
        dst = args.out / f"cover-{c:g}"
        runs.append((f"{c:g}", occlude(args.site / "seq_00", args.texture_site / "seq_00", dst, c, args.seed), dst))
    print("| passers-by (share of width) | pixels covered | method | frames | APE t cm | APE r deg | FPS |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for name, covered, seq in runs:
        for method in ("rm", "pnl"):
            s = localize(args.site, seq, method, args.out / f"{name}-{method}.txt")
            print(f"| {name} | {100 * covered:.0f} % | {method} | {s['localized']}/{s['frames']} | "
                  f"{100 * s['ape_none_trans_rmse_m']:.2f} | {s['ape_none_rot_rmse_deg']:.3f} | {s['fps']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
