"""Regenerate the raw example: a stereo pair as a calibrated camera takes it, with its calibration.

    .venv/bin/python service/static/make_raw_example.py

A procedural scene (`stereo_data.synthetic`, a fixed seed) is rendered rectified (focal RENDER_FOCAL_PX,
baseline BASELINE_M), then seen by a known rig, as a real stereo camera's raw pair would be: each lens
has its own camera matrix and distortion, and the right camera is turned by about 1.3 degrees.
Written to `examples/raw-320x240/`: `left.png` and `right.png` (the raw pair), `stereo.yaml` (K1,
D1, K2, D2, R, T, image_width, image_height, written by cv2.FileStorage: what `--calibration` and
the service's `calibration` part read), `stereo.json` (the same in OpenCV's JSON, for the web page:
its server serves JSON, not YAML) and `depth_mm.png` (the scene's true depth along the left camera's
axis at the raw left pixels, 16-bit millimetres, 0 = none). `examples.json` (make_assets.py) lists it
with `stereo.json` as its calibration.

    .venv/bin/python service/static/make_raw_example.py --calibration-only   # the two calibration files only
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

STATIC = Path(__file__).resolve().parent
sys.path.insert(0, str(STATIC.parents[1]))  # the repository root, when run as a script

from crestereo_pp.stereo_data.formats import encode_depth_mm_png  # noqa: E402
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator  # noqa: E402

FOLDER = STATIC / "examples" / "raw-320x240"
WIDTH, HEIGHT = 320, 240
MARGIN = 32  # px rendered beyond the raw images on every side: distortion and the turn look past them
RENDER_FOCAL_PX, BASELINE_M = 300.0, 0.12
SEED = 21
K1 = np.array([[301.5, 0.0, 161.2], [0.0, 302.1, 118.4], [0.0, 0.0, 1.0]])
K2 = np.array([[298.8, 0.0, 157.6], [0.0, 299.3, 121.7], [0.0, 0.0, 1.0]])
D1 = np.array([-0.14, 0.06, 0.0008, -0.0005, 0.0])
D2 = np.array([-0.12, 0.05, -0.0006, 0.0004, 0.0])
TURN = cv2.Rodrigues(np.array([0.006, -0.02, 0.008]))[0]  # the right camera's turn: X_right = TURN @ X_before
R = TURN
T = TURN @ np.array([-BASELINE_M, 0.0, 0.0])  # metres: the right camera 12 cm to the right


def calibration_entries() -> dict[str, np.ndarray | int]:
    """The rig as OpenCV names it (cv2.stereoCalibrate's K1, D1, K2, D2, R, T) with its image size."""
    return {"K1": K1, "D1": D1, "K2": K2, "D2": D2, "R": R, "T": T, "image_width": WIDTH, "image_height": HEIGHT}


def seen_from(k: np.ndarray, d: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Where each pixel of a raw view (camera matrix k, distortion d, turned by `turn` from its
    rectified camera) lies in the rectified render: float32 HxWx2."""
    render = np.array([[RENDER_FOCAL_PX, 0, (WIDTH - 1) / 2 + MARGIN], [0, RENDER_FOCAL_PX, (HEIGHT - 1) / 2 + MARGIN]])
    pixels = np.stack(np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT)), -1).reshape(-1, 1, 2).astype(np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)
    seen = cv2.undistortPoints(pixels, k, d, R=turn.T, P=np.vstack([render, [0, 0, 1]]), criteria=criteria)
    return seen.reshape(HEIGHT, WIDTH, 2).astype(np.float32)


def render() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The raw pair (uint8 HxWx3 RGB) and the true depth at the raw left pixels (metres, float32 HxW)."""
    config = SceneConfig(
        height=HEIGHT + 2 * MARGIN, width=WIDTH + 2 * MARGIN, max_disparity=WIDTH / 6, photometric=None
    )
    batch = SceneGenerator(config).generate(batch_size=1, seed=SEED)
    left, right = batch.pair()
    depth = RENDER_FOCAL_PX * BASELINE_M / batch.disparity[0, 0].numpy()
    at_left, at_right = seen_from(K1, D1, np.eye(3)), seen_from(K2, D2, TURN)
    raw_left, raw_right = (
        cv2.remap(image, seen[..., 0], seen[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        for image, seen in ((left, at_left), (right, at_right))
    )
    raw_depth = cv2.remap(depth.astype(np.float32), at_left[..., 0], at_left[..., 1], cv2.INTER_NEAREST)
    return raw_left, raw_right, raw_depth


def write_calibration() -> None:
    """`stereo.yaml` and `stereo.json`: the rig, in OpenCV's YAML and JSON."""
    for name in ("stereo.yaml", "stereo.json"):
        storage = cv2.FileStorage(str(FOLDER / name), cv2.FILE_STORAGE_WRITE)
        for key, value in calibration_entries().items():
            storage.write(key, value)
        storage.release()


def main() -> None:
    FOLDER.mkdir(parents=True, exist_ok=True)
    write_calibration()
    if "--calibration-only" in sys.argv[1:]:
        return
    left, right, depth = render()
    smallest = [cv2.IMWRITE_PNG_COMPRESSION, 9]
    for name, image in (("left", left), ("right", right)):
        assert cv2.imwrite(str(FOLDER / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), smallest)
    (FOLDER / "depth_mm.png").write_bytes(encode_depth_mm_png(depth))


if __name__ == "__main__":
    main()
