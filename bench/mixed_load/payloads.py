"""What the clients send, encoded once before the load starts (the client's CPU stays low): the dev
pairs at their own sizes, crops and rescales of them at many distinct sizes, small crops for `full`,
raw pairs with their calibrations, the frames of a stream, and the malformed uploads."""

from __future__ import annotations

import os
import random
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = Path(os.environ.get("STEREO_DEV", "/work/shared/data/stereo-dev"))
RAW_EXAMPLE = REPO / "service" / "static" / "examples" / "raw-320x240"


@dataclass(frozen=True)
class Pair:
    """A pair's encoded files (and, for a raw pair, its calibration file)."""

    name: str
    width: int
    height: int
    left: bytes
    right: bytes
    calibration: bytes | None = None
    image_type: str = "image/png"

    def files(self) -> list[tuple[str, tuple[str, bytes, str]]]:
        ext = "png" if self.image_type == "image/png" else "jpg"
        parts = [
            ("left", (f"left.{ext}", self.left, self.image_type)),
            ("right", (f"right.{ext}", self.right, self.image_type)),
        ]
        if self.calibration is not None:
            parts.append(("calibration", ("stereo.yaml", self.calibration, "application/x-yaml")))
        return parts


@dataclass
class Payloads:
    dev: list[Pair]
    variants: list[Pair]
    small: list[Pair]  # crops of at most 384x288, for `full`
    raw: list[Pair]
    stream_frames: list[Pair]
    bad_calibration: Pair
    mismatch: Pair

    def sizes(self) -> set[tuple[int, int]]:
        """The distinct image sizes of the pairs computed (dev, variants, small, raw)."""
        return {(p.width, p.height) for p in (*self.dev, *self.variants, *self.small, *self.raw)}


def encode(image: np.ndarray, ext: str = ".png", flags: list[int] | None = None) -> bytes:
    """`image` as an `ext` file, written with cv2's `flags` (by default: JPEG at quality 92, PNG as cv2 does)."""
    if flags is None:
        flags = [cv2.IMWRITE_JPEG_QUALITY, 92] if ext == ".jpg" else []
    ok, data = cv2.imencode(ext, image, flags)
    if not ok:
        raise RuntimeError(f"cv2 could not encode a {image.shape} image as {ext}")
    return data.tobytes()


def as_pair(
    name: str, left: np.ndarray, right: np.ndarray, ext: str = ".png", calibration: bytes | None = None
) -> Pair:
    height, width = left.shape[:2]
    image_type = "image/png" if ext == ".png" else "image/jpeg"
    return Pair(name, width, height, encode(left, ext), encode(right, ext), calibration, image_type)


def calibration_yaml(
    k1: np.ndarray, d1: np.ndarray, k2: np.ndarray, d2: np.ndarray, r: np.ndarray, t: np.ndarray, size: tuple[int, int]
) -> bytes:
    """An OpenCV stereo calibration file, as cv2.FileStorage writes it."""
    storage = cv2.FileStorage("calibration.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    for key, value in (("K1", k1), ("D1", d1), ("K2", k2), ("D2", d2), ("R", r), ("T", t)):
        storage.write(key, np.asarray(value, np.float64))
    storage.write("image_width", size[0])
    storage.write("image_height", size[1])
    return storage.releaseAndGetString().encode()


def pinhole_calibration(width: int, height: int, focal: float, baseline_m: float = 0.12) -> bytes:
    """A calibration of an already rectified camera (no distortion, no rotation) of this size."""
    k = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    return calibration_yaml(k, np.zeros(5), k, np.zeros(5), np.eye(3), np.array([-baseline_m, 0, 0]), (width, height))


def read(path: Path) -> np.ndarray:
    image = cv2.imread(str(path))
    if image is None:
        raise SystemExit(f"cannot read {path}")
    return np.asarray(image)


Images = list[tuple[str, np.ndarray, np.ndarray]]


def variants_of(images: Images, count: int, taken: set[tuple[int, int]], rng: random.Random) -> list[Pair]:
    """`count` crops (of rescales, half of them) of the pairs, each of a size not in `taken`; a
    third of them JPEG."""
    out: list[Pair] = []
    while len(out) < count:
        name, left, right = rng.choice(images)
        height, width = left.shape[:2]
        if rng.random() < 0.5:  # rescaled, then maybe cropped
            factor = rng.uniform(0.3, 0.95)
            size = (max(64, round(width * factor)), max(64, round(height * factor)))
            left, right = (cv2.resize(image, size, interpolation=cv2.INTER_AREA) for image in (left, right))
            height, width = left.shape[:2]
        crop_w, crop_h = rng.randint(min(96, width), width), rng.randint(min(64, height), height)
        if (crop_w, crop_h) in taken:
            continue
        taken.add((crop_w, crop_h))
        x, y = rng.randint(0, width - crop_w), rng.randint(0, height - crop_h)
        window = (slice(y, y + crop_h), slice(x, x + crop_w))
        ext = ".jpg" if rng.random() < 0.3 else ".png"
        out.append(as_pair(f"{name}:{crop_w}x{crop_h}", left[window], right[window], ext))
    return out


def small_crops(images: Images, rng: random.Random) -> list[Pair]:
    """The top-left corners of the first 8 pairs, at most 384x288 (a multiple of 8 px less, at random)."""
    small = []
    for name, left, right in images[:8]:
        crop_w, crop_h = (
            min(384, left.shape[1]) - rng.randrange(0, 64, 8),
            min(288, left.shape[0]) - rng.randrange(0, 64, 8),
        )
        small.append(as_pair(f"{name}:{crop_w}x{crop_h}", left[:crop_h, :crop_w], right[:crop_h, :crop_w]))
    return small


def build_payloads(data: Path, variants: int, calibrations: int, rng: random.Random) -> Payloads:
    folders = sorted(path.parent for path in data.glob("*/left.png"))
    if not folders:
        raise SystemExit(f"no pairs (*/left.png, */right.png) under {data}")
    images = [(f.name, read(f / "left.png"), read(f / "right.png")) for f in folders]
    dev = [as_pair(name, left, right) for name, left, right in images]
    out = variants_of(images, variants, {(p.width, p.height) for p in dev}, rng)
    small = small_crops(images, rng)

    raw_left, raw_right = (read(RAW_EXAMPLE / f"{side}.png") for side in ("left", "right"))
    storage = cv2.FileStorage(str(RAW_EXAMPLE / "stereo.yaml"), cv2.FILE_STORAGE_READ)
    k1, d1, k2, d2, r, t = (storage.getNode(key).mat() for key in ("K1", "D1", "K2", "D2", "R", "T"))
    storage.release()
    raw = []
    for i in range(calibrations):  # the example camera with its focal lengths nudged: one rectifier each
        nudge = np.diag([1 + 0.004 * i, 1 + 0.004 * i, 1])
        yaml = calibration_yaml(nudge @ k1, d1, nudge @ k2, d2, r, t, (320, 240))
        raw.append(as_pair(f"raw-320x240#{i}", raw_left, raw_right, calibration=yaml))
    for i in range(calibrations):  # cameras of dev pairs' sizes, spread over the set: larger maps
        name, left, right = images[i * len(images) // calibrations]
        height, width = left.shape[:2]
        raw.append(as_pair(f"raw-{name}", left, right, calibration=pinhole_calibration(width, height, 700.0 + 10 * i)))

    name, left, right = next(image for image in images if image[1].shape[0] >= 240 and image[1].shape[1] >= 400)
    stream_frames = [
        as_pair(f"{name}:frame{dx}", left[:224, dx : dx + 320], right[:224, dx : dx + 320]) for dx in range(0, 80, 16)
    ]

    bad_t = calibration_yaml(k1, d1, k2, d2, r, np.zeros(3), (320, 240))  # zero baseline: invalid_calibration
    bad_calibration = as_pair("bad-calibration", raw_left, raw_right, calibration=bad_t)
    name, left, right = images[0]
    mismatch = Pair("size-mismatch", 0, 0, encode(left), encode(right[:, :-8]))
    return Payloads(dev, out, small, raw, stream_frames, bad_calibration, mismatch)
