"""Camera sequences: TUM RGB-D style folders plus ``camera.json``, and video files.

Folder layout (``docs/CONVENTIONS.md``)::

    <sequence>/rgb/<timestamp>.jpg|png
    <sequence>/rgb.txt           "timestamp rgb/<file>" per line, '#' comments (without it: rgb/'s images
                                 named by timestamp, in time order)
    <sequence>/camera.json       intrinsics
    <sequence>/groundtruth.txt   optional TUM camera-to-world poses

A video file (``.mp4``, ``.avi``, ...) is read frame by frame; its timestamps are the
container's presentation times in seconds, written with 6 decimals. It needs a
``camera.json`` beside it (``<video>.camera.json`` or ``camera.json``) or one passed in.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.io.atomic import atomic_write_bytes, atomic_write_text
from services.io.stamps import seconds_per_unit
from services.io.trajectory import Trajectory, read_tum, write_tum

__all__ = ["Frame", "Sequence", "SequenceError", "SequenceWriter", "open_sequence", "VIDEO_SUFFIXES"]

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v"}


class SequenceError(ValueError):
    """A sequence that cannot be read; the message names the file and the problem."""


@dataclass(frozen=True)
class Frame:
    stamp: str  # exact timestamp text from rgb.txt
    image: np.ndarray | None  # HxWx3 uint8, BGR (OpenCV order); None only with ``problem``
    problem: str | None = None  # why the image could not be read (``Sequence.frames(tolerant=True)`` only)


class Sequence:
    """A readable camera sequence (folder or video)."""

    def __init__(self, root: Path, camera: Camera, stamps: list[str], files: list[Path] | None,
                 groundtruth: Trajectory | None, video: Path | None = None):
        self.root = root
        self.camera = camera
        self.stamps = stamps
        self.files = files
        self.groundtruth = groundtruth
        self.video = video
        # the capture time's unit (services.io.stamps): seconds, or what a recorder that counts finer used
        self.seconds_per_unit, self.stamp_unit = seconds_per_unit(stamps, f"{root if video is None else video}: timestamps")

    @property
    def name(self) -> str:
        return self.root.name if self.video is None else self.video.stem

    def __len__(self) -> int:
        return len(self.stamps)

    def seconds(self, stamp: str) -> float | None:
        """A frame's capture time in seconds (its timestamp text in the sequence's unit), None if not a number."""
        try:
            return float(stamp) * self.seconds_per_unit
        except ValueError:
            return None

    def read(self, i: int) -> Frame:
        if self.files is None:
            raise SequenceError("random access is not supported for video; iterate instead")
        path = self.files[i]
        if not path.exists():
            raise SequenceError(f"{path}: missing")
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise SequenceError(f"{path}: cannot decode image")
        if img.shape[1] != self.camera.width or img.shape[0] != self.camera.height:
            raise SequenceError(
                f"{path}: image is {img.shape[1]}x{img.shape[0]} but camera.json says {self.camera.width}x{self.camera.height}")
        return Frame(self.stamps[i], img)

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def frames(self, tolerant: bool = False) -> Iterator[Frame]:
        """The frames in order. ``tolerant``: an image file that is missing or cannot be decoded (a recorder's dropped
        or truncated write) comes as a Frame with no image and its ``problem``, logged, instead of ending the
        iteration with a SequenceError; a frame of another size than camera.json's still raises."""
        if self.video is None:
            for i in range(len(self)):
                try:
                    yield self.read(i)
                except SequenceError as e:
                    if not tolerant or "camera.json says" in str(e):
                        raise
                    log.warning("frame %s skipped: %s", self.stamps[i], e)
                    yield Frame(self.stamps[i], None, str(e))
            return
        cap = cv2.VideoCapture(str(self.video))
        try:
            for stamp in self.stamps:
                ok, img = cap.read()
                if not ok:
                    break
                yield Frame(stamp, img)
        finally:
            cap.release()

    def groundtruth_pose(self, stamp: str) -> Pose | None:
        if self.groundtruth is None:
            return None
        return self.groundtruth.as_dict().get(stamp)


IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}


def _listed_by_name(path: Path) -> list[tuple[str, str]]:
    """Without rgb.txt: the images of rgb/ named by their timestamp (``rgb/<timestamp>.jpg|png``, as the layout names
    them), in time order; a SequenceError when there is no rgb/ or its images are named otherwise."""
    folder = path.parent / "rgb"
    images = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    if not images:
        raise SequenceError(f"{path}: missing (a sequence folder needs rgb.txt, or rgb/ with images named by timestamp)")
    stamped = []
    for f in images:
        try:
            stamped.append((float(f.stem), f.stem, f"rgb/{f.name}"))
        except ValueError:
            raise SequenceError(f"{path}: missing, and the images of rgb/ are not named by timestamp (e.g. {f.name}): "
                                "write rgb.txt, lines 'timestamp rgb/<file>'") from None
    stamped.sort(key=lambda x: x[0])
    log.info("%s: no rgb.txt; the %d images of rgb/ taken in timestamp order (their names)", path.parent, len(stamped))
    return [(stem, rel) for _, stem, rel in stamped]


def _read_rgb_txt(path: Path) -> list[tuple[str, str]]:
    if not path.exists():
        return _listed_by_name(path)
    entries, unordered, last = [], [], 0.0
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise SequenceError(f"{path}:{n}: expected 'timestamp rgb/<file>', got {line!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise SequenceError(f"{path}:{n}: timestamp {parts[0]!r} is not a number") from None
        if entries and t <= last:
            unordered.append((n, parts[0], entries[-1][0]))
        entries.append((parts[0], parts[1]))
        last = t
    if not entries:
        raise SequenceError(f"{path}: lists no frames")
    if unordered:  # tracking takes frames as they come: a motion model cannot run backwards, a trajectory file repeats
        n, now, before = unordered[0]
        log.warning("%s: %d timestamp(s) do not increase, the first on line %d (%s after %s): frames are localized in "
                    "file order; sort the file by time", path, len(unordered), n, now, before)
    return entries


def _find_camera(candidates: list[Path]) -> Camera:
    for c in candidates:
        if c.exists():
            return Camera.load(c)
    raise SequenceError(f"no camera.json found (looked for {', '.join(str(c) for c in candidates)}); write one "
                        '({"width", "height", "fx", "fy", "cx", "cy", "distortion": [k1, k2, p1, p2, k3]}) or pass --camera')


def _fitted(cam: Camera, width: int, height: int, source: Path) -> Camera:
    """``cam`` for images of ``width`` x ``height``: itself when they are its size; scaled when they are the same picture
    at another resolution (the same aspect to a pixel: intrinsics taken at a phone's capture size, video recorded
    smaller), with a warning; else itself, and reading a frame says what does not fit."""
    if (width, height) == (cam.width, cam.height) or width <= 0 or height <= 0:
        return cam
    s = width / cam.width
    if abs(cam.height * s - height) > 0.5:
        return cam
    scaled = cam.scaled(s)
    if (scaled.width, scaled.height) != (width, height):
        return cam
    log.warning("%s: images are %dx%d, camera.json says %dx%d: the same picture at %.3g x the resolution, so its "
                "intrinsics are scaled (fx %.1f -> %.1f); if the images are cropped, give a camera.json for them",
                source, width, height, cam.width, cam.height, s, cam.fx, scaled.fx)
    return scaled


def open_sequence(source: str | Path, camera: Camera | None = None) -> Sequence:
    """Open a sequence folder or a video file. Intrinsics for another resolution of the same picture are scaled to
    the images' (:func:`_fitted`)."""
    src = Path(source)
    if not src.exists():
        raise SequenceError(f"{src}: no such sequence folder or video file")
    if src.is_file():
        if src.suffix.lower() not in VIDEO_SUFFIXES:
            raise SequenceError(f"{src}: not a sequence folder nor a video file ({', '.join(sorted(VIDEO_SUFFIXES))})")
        cam = camera or _find_camera([src.with_suffix(".camera.json"), src.parent / "camera.json"])
        cap = cv2.VideoCapture(str(src))
        if not cap.isOpened():
            raise SequenceError(f"{src}: cannot open video")
        cam = _fitted(cam, int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), src)
        stamps = []
        while cap.grab():
            stamps.append(f"{cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0:.6f}")
        cap.release()
        if not stamps:
            raise SequenceError(f"{src}: video has no frames")
        gt_path = src.with_suffix(".groundtruth.txt")
        gt = read_tum(gt_path) if gt_path.exists() else None
        return Sequence(src.parent, cam, stamps, None, gt, video=src)
    cam = camera or _find_camera([src / "camera.json"])
    entries = _read_rgb_txt(src / "rgb.txt")
    files = [src / rel for _, rel in entries]
    missing = [f for f in files if not f.exists()]
    if len(missing) == len(files):
        raise SequenceError(f"{src}: all {len(missing)} image(s) listed in rgb.txt are missing, e.g. {missing[0]}")
    if missing:  # a recorder that dropped a few writes: the rest is worth localizing (Sequence.frames(tolerant=True))
        log.warning("%s: %d of %d image(s) listed in rgb.txt are missing, e.g. %s", src, len(missing), len(files),
                    missing[0])
    first = next((cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files if f.exists()), None)
    if first is not None:
        cam = _fitted(cam, first.shape[1], first.shape[0], src)
    gt_path = src / "groundtruth.txt"
    gt = read_tum(gt_path) if gt_path.exists() else None
    return Sequence(src, cam, [s for s, _ in entries], files, gt)


class SequenceWriter:
    """Writes a sequence folder frame by frame; ``rgb.txt`` and ``groundtruth.txt`` are written atomically on close."""

    def __init__(self, root: str | Path, camera: Camera, ext: str = ".jpg", jpeg_quality: int = 90):
        self.root = Path(root)
        (self.root / "rgb").mkdir(parents=True, exist_ok=True)
        self.camera = camera
        self.ext = ext
        self.jpeg_quality = jpeg_quality
        self.entries: list[tuple[str, str]] = []
        self.gt = Trajectory()
        camera.save(self.root / "camera.json")

    def add(self, stamp: str, image_bgr: np.ndarray, T_wc: Pose | None = None) -> None:
        rel = f"rgb/{stamp}{self.ext}"
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.ext == ".jpg" else []
        ok, buf = cv2.imencode(self.ext, image_bgr, params)
        if not ok:
            raise SequenceError(f"cannot encode frame {stamp}")
        atomic_write_bytes(self.root / rel, buf.tobytes())
        self.entries.append((stamp, rel))
        if T_wc is not None:
            self.gt.append(stamp, T_wc)

    def close(self) -> None:
        lines = ["# color images", "# timestamp filename"] + [f"{s} {r}" for s, r in self.entries]
        atomic_write_text(self.root / "rgb.txt", "\n".join(lines) + "\n")
        if len(self.gt):
            write_tum(self.root / "groundtruth.txt", self.gt, header="ground truth camera-to-world\ntimestamp tx ty tz qx qy qz qw")

    def __enter__(self) -> "SequenceWriter":
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()
