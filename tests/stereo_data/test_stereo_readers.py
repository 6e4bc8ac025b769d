"""Spec of stereo_data.readers: each on-disk layout, auto-detection, laziness, the real dev pairs."""

import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from crestereo_pp.stereo_data.formats import FormatError, write_kitti_disparity, write_pfm
from crestereo_pp.stereo_data.readers import LAYOUTS, StereoSample, open_dataset
from shared_data import STEREO_DEV

HEIGHT, WIDTH = 6, 10


def pair(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random RGB pair and a disparity map on the 1/256 grid (exact in KITTI PNG) with holes."""
    rng = np.random.default_rng(seed)
    left = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    right = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    disparity = np.round(rng.uniform(0.5, 60, (HEIGHT, WIDTH)) * 256).astype(np.float32) / 256
    disparity[0, :3] = np.inf
    return left, right, disparity


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def write_gray(path: Path, gray: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), gray)


def nonocc_mask(disparity: np.ndarray) -> np.ndarray:
    """Middlebury-style mask0nocc: 255 visible, 128 occluded (column 9 here), 0 unknown."""
    mask = np.full(disparity.shape, 255, dtype=np.uint8)
    mask[:, 9] = 128
    mask[~np.isfinite(disparity)] = 0
    return mask


def make_middlebury2014(root: Path, names: list[str]) -> None:
    for seed, name in enumerate(names):
        left, right, disparity = pair(seed)
        write_rgb(root / name / "im0.png", left)
        write_rgb(root / name / "im1.png", right)
        write_pfm(root / name / "disp0GT.pfm", disparity)
        write_gray(root / name / "mask0nocc.png", nonocc_mask(disparity))


def make_eth3d(root: Path, names: list[str]) -> None:
    for seed, name in enumerate(names):
        left, right, disparity = pair(seed)
        write_gray(root / name / "im0.png", left[..., 0])
        write_gray(root / name / "im1.png", right[..., 0])
        write_pfm(root / name / "disp0GT.pfm", disparity)
        write_gray(root / name / "mask0nocc.png", nonocc_mask(disparity))


def kitti_maker(left: str, right: str, occ: str, noc: str) -> Callable[[Path, list[str]], None]:
    def make(root: Path, names: list[str]) -> None:
        for seed, name in enumerate(names):
            left_image, right_image, disparity = pair(seed)
            write_rgb(root / left / f"{name}.png", left_image)
            write_rgb(root / right / f"{name}.png", right_image)
            write_rgb(root / left / f"{name[:-3]}_11.png", right_image)  # next frame: no GT
            (root / occ).mkdir(exist_ok=True)
            write_kitti_disparity(root / occ / f"{name}.png", disparity)
            (root / noc).mkdir(exist_ok=True)
            non_occluded = disparity.copy()
            non_occluded[:, 9] = np.inf
            write_kitti_disparity(root / noc / f"{name}.png", non_occluded)

    return make


def make_sceneflow(root: Path, names: list[str]) -> None:
    for seed, name in enumerate(names):
        left, right, disparity = pair(seed)
        sequence, frame = name.rsplit("/", 1)
        write_rgb(root / "frames_cleanpass" / sequence / "left" / f"{frame}.png", left)
        write_rgb(root / "frames_cleanpass" / sequence / "right" / f"{frame}.png", right)
        (root / "disparity" / sequence / "left").mkdir(parents=True, exist_ok=True)
        write_pfm(root / "disparity" / sequence / "left" / f"{frame}.pfm", disparity)


def make_simple(root: Path, names: list[str]) -> None:
    for seed, name in enumerate(names):
        left, right, disparity = pair(seed)
        write_rgb(root / name / "left.png", left)
        write_rgb(root / name / "right.png", right)
        write_pfm(root / name / "disp.pfm", disparity)


KITTI_NAMES = ["000000_10", "000001_10"]
LAYOUT_FIXTURES = {
    "middlebury2014": (make_middlebury2014, ["Adirondack", "Motorcycle"]),
    "eth3d": (make_eth3d, ["delivery_area_1l", "electro_1s"]),
    "kitti2012": (kitti_maker("colored_0", "colored_1", "disp_occ", "disp_noc"), KITTI_NAMES),
    "kitti2015": (kitti_maker("image_2", "image_3", "disp_occ_0", "disp_noc_0"), KITTI_NAMES),
    "sceneflow": (make_sceneflow, ["TRAIN/A/0000/0006", "TRAIN/C/0001/0010"]),
    "simple": (make_simple, ["pair_a", "pair_b"]),
}


def test_every_layout_has_a_fixture() -> None:
    assert set(LAYOUT_FIXTURES) == set(LAYOUTS)


@pytest.mark.parametrize("layout", sorted(LAYOUT_FIXTURES))
def test_layout_is_detected_and_samples_read_back_exactly(tmp_path: Path, layout: str) -> None:
    make, names = LAYOUT_FIXTURES[layout]
    make(tmp_path, names)
    dataset = open_dataset(tmp_path)
    assert dataset.layout == layout and len(dataset) == 2
    assert [sample.name for sample in dataset] == names
    for seed, sample in enumerate(dataset):
        left, right, disparity = pair(seed)
        assert isinstance(sample, StereoSample)
        assert sample.left.dtype == np.uint8 and sample.left.shape == (HEIGHT, WIDTH, 3)
        if layout == "eth3d":  # grayscale on disk, replicated to RGB
            left, right = (np.repeat(image[..., :1], 3, 2) for image in (left, right))
        np.testing.assert_array_equal(sample.left, left)
        np.testing.assert_array_equal(sample.right, right)
        assert sample.disparity.dtype == np.float32
        np.testing.assert_array_equal(sample.disparity, disparity)
        np.testing.assert_array_equal(sample.valid, np.isfinite(disparity))


@pytest.mark.parametrize("layout", ["middlebury2014", "eth3d", "kitti2012", "kitti2015"])
def test_non_occluded_mask_is_read_where_the_layout_has_one(tmp_path: Path, layout: str) -> None:
    make, names = LAYOUT_FIXTURES[layout]
    make(tmp_path, names)
    sample = open_dataset(tmp_path, layout)[0]
    expected = np.isfinite(pair(0)[2])
    expected[:, 9] = False
    assert sample.nonoccluded is not None
    np.testing.assert_array_equal(sample.nonoccluded, expected)


@pytest.mark.parametrize("layout", ["sceneflow", "simple"])
def test_non_occluded_mask_is_none_where_the_layout_has_none(tmp_path: Path, layout: str) -> None:
    make, names = LAYOUT_FIXTURES[layout]
    make(tmp_path, names)
    assert open_dataset(tmp_path)[0].nonoccluded is None


def test_sceneflow_reader_accepts_any_nesting_and_prefers_the_clean_pass(tmp_path: Path) -> None:
    names = [
        "TEST/B/0150/0007",  # FlyingThings3D
        "15mm_focallength/scene_forwards/fast/0001",  # Driving
        "a_rain_of_stones_x2/0000",  # Monkaa
    ]
    make_sceneflow(tmp_path, names)
    (tmp_path / "frames_finalpass").mkdir()
    assert sorted(sample.name for sample in open_dataset(tmp_path, "sceneflow")) == sorted(names)


def test_sceneflow_reader_falls_back_to_the_final_pass(tmp_path: Path) -> None:
    make_sceneflow(tmp_path, ["TRAIN/A/0000/0006"])
    (tmp_path / "frames_cleanpass").rename(tmp_path / "frames_finalpass")
    assert open_dataset(tmp_path).layout == "sceneflow"


def test_kitti_reader_accepts_the_folder_holding_training(tmp_path: Path) -> None:
    make, names = LAYOUT_FIXTURES["kitti2015"]
    make(tmp_path / "training", names)
    assert len(open_dataset(tmp_path, "kitti2015")) == 2


def test_samples_without_both_images_are_not_listed(tmp_path: Path) -> None:
    make_simple(tmp_path, ["pair_a", "pair_b"])
    (tmp_path / "pair_b" / "right.png").unlink()
    assert [sample.name for sample in open_dataset(tmp_path)] == ["pair_a"]


def test_dataset_reads_files_only_when_a_sample_is_asked_for(tmp_path: Path) -> None:
    make_simple(tmp_path, ["pair_a", "pair_b"])
    dataset = open_dataset(tmp_path)
    (tmp_path / "pair_b" / "disp.pfm").write_bytes(b"garbage")
    assert dataset[0].name == "pair_a"
    with pytest.raises(FormatError, match="disp.pfm"):
        dataset[1]


def test_dataset_supports_negative_indices_and_slices(tmp_path: Path) -> None:
    make_simple(tmp_path, ["a", "b", "c"])
    dataset = open_dataset(tmp_path)
    assert dataset[-1].name == "c"
    assert [sample.name for sample in dataset[1:]] == ["b", "c"]
    with pytest.raises(IndexError):
        dataset[3]


def test_sample_with_mismatched_sizes_is_rejected(tmp_path: Path) -> None:
    make_simple(tmp_path / "simple", ["a"])
    write_rgb(tmp_path / "simple" / "a" / "right.png", np.zeros((HEIGHT + 1, WIDTH, 3), np.uint8))
    make_middlebury2014(tmp_path / "middlebury", ["Adirondack"])
    write_gray(tmp_path / "middlebury" / "Adirondack" / "mask0nocc.png", np.zeros((2, 2), np.uint8))
    for root in (tmp_path / "simple", tmp_path / "middlebury"):
        with pytest.raises(FormatError, match="differ in size"):
            open_dataset(root)[0]


def test_nan_ground_truth_counts_as_unknown(tmp_path: Path) -> None:
    make_simple(tmp_path, ["a"])
    disparity = pair(0)[2]
    disparity[2, 2] = np.nan
    write_pfm(tmp_path / "a" / "disp.pfm", disparity)
    sample = open_dataset(tmp_path)[0]
    assert sample.disparity[2, 2] == np.inf and not sample.valid[2, 2]


def test_unrecognised_folder_error_lists_the_supported_layouts(tmp_path: Path) -> None:
    (tmp_path / "something.txt").write_text("hello")
    with pytest.raises(FormatError) as error:
        open_dataset(tmp_path)
    for layout in LAYOUTS:
        assert layout in str(error.value)


def test_explicit_layout_that_does_not_match_is_an_error(tmp_path: Path) -> None:
    make_simple(tmp_path, ["a"])
    with pytest.raises(FormatError, match="no kitti2015 samples"):
        open_dataset(tmp_path, "kitti2015")
    with pytest.raises(FormatError, match="unknown layout 'kitti'"):
        open_dataset(tmp_path, "kitti")
    with pytest.raises(FormatError, match="not a folder"):
        open_dataset(tmp_path / "nowhere")


# --- The real development pairs (/work/shared/data/stereo-dev, or $STEREO_DEV) ---------------------

needs_stereo_dev = pytest.mark.skipif(
    not STEREO_DEV.is_dir(), reason=f"stereo-dev pairs not found at {STEREO_DEV} (set STEREO_DEV to the folder)"
)


def warp_mae(sample: StereoSample, disparity: np.ndarray) -> float:
    """Mean abs grey difference between left and right warped by ``disparity`` (bilinear), over
    valid-GT pixels whose match lands inside the right image."""
    gray_left, gray_right = (
        cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) for image in (sample.left, sample.right)
    )
    height, width = disparity.shape
    x_match = np.arange(width, dtype=np.float32)[None, :] - disparity
    rows = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, 1)
    map_x = np.where(sample.valid, x_match, 0).astype(np.float32)
    warped = cv2.remap(gray_right, map_x, rows, cv2.INTER_LINEAR)
    inside = sample.valid & (x_match >= 0) & (x_match <= width - 1)
    return float(np.abs(warped - gray_left)[inside].mean())


@needs_stereo_dev
def test_stereo_dev_pairs_read_with_the_documented_ground_truth() -> None:
    dataset = open_dataset(STEREO_DEV)
    assert dataset.layout == "simple" and len(dataset) == 16
    for sample in dataset:
        meta = json.loads((STEREO_DEV / sample.name / "meta.json").read_text())
        size = (meta["resolution"]["height"], meta["resolution"]["width"])
        assert sample.left.shape == sample.right.shape == (*size, 3)
        assert sample.disparity.shape == sample.valid.shape == size
        assert sample.valid.mean() == pytest.approx(meta["valid_fraction"], abs=1e-3)
        assert sample.disparity[sample.valid].max() == pytest.approx(meta["max_disparity"], rel=1e-4)
    kitti2012 = next(sample for sample in dataset if sample.name == "kitti2012_000000_10")
    assert kitti2012.valid.mean() == pytest.approx(0.36, abs=0.01)


@needs_stereo_dev
def test_stereo_dev_right_warped_by_ground_truth_matches_left() -> None:
    """Same check as the pairs' meta.json: the GT warp error is the documented one, and far below
    the error with zero disparity."""
    for sample in open_dataset(STEREO_DEV):
        meta = json.loads((STEREO_DEV / sample.name / "meta.json").read_text())
        documented = meta["sanity_warp_check"]
        with_gt = warp_mae(sample, sample.disparity)
        assert with_gt == pytest.approx(documented["mae_gt_disp"], abs=0.05), sample.name
        assert with_gt < 0.4 * warp_mae(sample, np.zeros_like(sample.disparity)), sample.name
