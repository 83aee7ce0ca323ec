"""Other cameras' pictures of the same walk: grey, dark, noisy, tinted and vignetted copies, localized by both methods.

    python benchmarks/photometric.py [--site runs/bench-sim/office] [--frames 150]
                                     [--variants mono dark iso cast vignette] [--out runs/photometric]

The scan's colours are the scanner's, on its day; the live camera is another sensor under other light. Each variant
copies the first --frames of SITE/seq_00 into OUT/VARIANT/ (ground truth copied) with one change a real camera makes:

  mono      a monochrome sensor (robots, headsets' tracking cameras): grey in all three channels
  dark      a dim room at a fixed short exposure: a third of the light, gamma 1.3, read noise (mean grey ~23 of 255)
  iso       high gain: normal brightness, noise of 8 grey levels (luma) + 4 (per channel)
  cast      tungsten light with no white balance: blue x0.7, red x1.3
  vignette  a cheap lens: 60 % darker in the corners
  jpeg50    frames sent harder compressed, as a client on a thin link would: JPEG quality 50 ...
  jpeg25    ... and 25 (8x8 blocks, ringing at edges)

Then `cristal localize` runs Render & Match (SITE/reloc.npz) and Prebuild & Localize (SITE/map) over each copy and
over the original's same frames, each from a cold start, and a table prints frames localized, APE with no alignment
and FPS. OUT/variants.png shows one frame of each. Deterministic (fixed noise seed).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.occluders import localize  # noqa: E402
from services.io.sequence import SequenceWriter, open_sequence  # noqa: E402


def _mono(im: np.ndarray, rng) -> np.ndarray:
    return cv2.cvtColor(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)


def _dark(im: np.ndarray, rng) -> np.ndarray:
    x = 0.3 * (im.astype(np.float32) / 255.0) ** 1.3 + rng.normal(0, 0.015, im.shape)
    return np.clip(255 * x, 0, 255).astype(np.uint8)


def _iso(im: np.ndarray, rng) -> np.ndarray:
    x = im.astype(np.float32) + rng.normal(0, 8, im.shape[:2])[..., None] + rng.normal(0, 4, im.shape)
    return np.clip(x, 0, 255).astype(np.uint8)


def _cast(im: np.ndarray, rng) -> np.ndarray:
    return np.clip(im.astype(np.float32) * np.array([0.7, 0.95, 1.3], np.float32), 0, 255).astype(np.uint8)


def _vignette(im: np.ndarray, rng) -> np.ndarray:
    h, w = im.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    return np.clip(im.astype(np.float32) * (1 - 0.6 * r2)[..., None], 0, 255).astype(np.uint8)


VARIANTS = {"original": lambda im, rng: im, "mono": _mono, "dark": _dark, "iso": _iso, "cast": _cast, "vignette": _vignette,
            "jpeg50": lambda im, rng: im, "jpeg25": lambda im, rng: im}
QUALITY = {"jpeg50": 50, "jpeg25": 25}  # the variant's JPEG quality (the others are written at the writer's 90)


def make_variant(src: Path, out: Path, name: str, frames: int, seed: int = 0) -> np.ndarray:
    """Writes the first ``frames`` of sequence ``src``, changed as variant ``name``, to ``out``; returns the middle
    frame as written (for the contact sheet)."""
    seq, rng = open_sequence(src), np.random.default_rng(seed)
    n = min(frames, len(seq))
    shown = None
    with SequenceWriter(out, seq.camera, jpeg_quality=QUALITY.get(name, 90)) as writer:
        for i in range(n):
            f = seq.read(i)
            img = VARIANTS[name](f.image, rng)
            writer.add(seq.stamps[i], img, seq.groundtruth_pose(f.stamp) if seq.groundtruth is not None else None)
            if i == n // 2:
                shown = cv2.imread(str(out / writer.entries[-1][1])) if name in QUALITY else img  # (as compressed)
    return shown


def contact_sheet(images: dict[str, np.ndarray], path: Path) -> None:
    tiles = []
    for name, im in images.items():
        t = cv2.resize(im, (320, int(320 * im.shape[0] / im.shape[1])))
        cv2.putText(t, name, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 255, 255), 2)
        tiles.append(t)
    while len(tiles) % 3:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + 3]) for i in range(0, len(tiles), 3)]
    cv2.imwrite(str(path), np.vstack(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", type=Path, default=Path("runs/bench-sim/office"))
    ap.add_argument("--frames", type=int, default=150, help="frames from the start of the walk (default 150)")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS)[1:], default=list(VARIANTS)[1:])
    ap.add_argument("--methods", nargs="+", choices=["rm", "pnl"], default=["rm", "pnl"])
    ap.add_argument("--out", type=Path, default=Path("runs/photometric"))
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    src = args.site / "seq_00"
    runs, shown = [], {}
    for name in ["original", *args.variants]:  # the original's same frames too, so each row compares like with like
        dst = args.out / name
        shown[name] = make_variant(src, dst, name, args.frames)
        runs.append((name, dst))
    args.out.mkdir(parents=True, exist_ok=True)
    contact_sheet(shown, args.out / "variants.png")
    print("| camera | method | frames | APE t cm | APE r deg | FPS |")
    print("|---|---|---:|---:|---:|---:|")
    for name, seq in runs:
        for method in args.methods:
            s = localize(args.site, seq, method, args.out / f"{name}-{method}.txt")
            print(f"| {name} | {method} | {s['localized']}/{s['frames']} | {100 * s['ape_none_trans_rmse_m']:.2f} | "
                  f"{s['ape_none_rot_rmse_deg']:.3f} | {s['fps']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
