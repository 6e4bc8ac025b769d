"""Readers for stereo datasets on disk, each a lazily loading ``Sequence[StereoSample]``.

Supported layouts (``root`` is the folder named in each line):

- ``middlebury2014``: ``root/SCENE/{im0.png, im1.png, disp0GT.pfm, mask0nocc.png}``
- ``eth3d``: the same files as Middlebury 2014, with grayscale images (ETH3D two-view)
- ``kitti2012``: ``root/{colored_0, colored_1, disp_occ}/NNNNNN_10.png`` (optional ``disp_noc/``)
- ``kitti2015``: ``root/{image_2, image_3, disp_occ_0}/NNNNNN_10.png`` (optional ``disp_noc_0/``)
- ``sceneflow``: ``root/frames_cleanpass/.../left/NNNN.png`` (or ``frames_finalpass``), ``.../right/``
  and ``root/disparity/.../left/NNNN.pfm``, at any nesting (TRAIN/TEST, A/B/C, sequence)
- ``simple``: ``root/NAME/{left.png, right.png, disp.pfm}`` (the stereo-dev layout, ``+inf`` invalid)

The KITTI readers also accept the folder that contains ``training/``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np

from crestereo_pp.stereo_data.formats import FormatError, read_image, read_kitti_disparity, read_pfm

__all__ = ["StereoSample", "StereoDataset", "open_dataset", "LAYOUTS"]


@dataclass(frozen=True)
class StereoSample:
    """One rectified pair with ground truth.

    left, right: uint8 HxWx3 RGB.
    disparity: float32 HxW, pixels of the LEFT image, positive; the match of left pixel (x, y) is
        right pixel (x - d, y). ``+inf`` where unknown.
    valid: bool HxW, True where the ground truth is known (``isfinite(disparity)``).
    nonoccluded: bool HxW, True where the pixel is known and visible in the right view; None when
        the layout does not say (SceneFlow, simple).
    """

    name: str
    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    valid: np.ndarray
    nonoccluded: np.ndarray | None = None


@dataclass(frozen=True)
class SampleFiles:
    """Where one sample lives on disk."""

    name: str
    left: Path
    right: Path
    disparity: Path
    nonoccluded: Path | None = None


@dataclass(frozen=True)
class _Layout:
    """A dataset layout: how to list its samples and how to decode their files."""

    find: Callable[[Path], list[SampleFiles]]
    read_disparity: Callable[[Path], np.ndarray]
    read_nonoccluded: Callable[[Path], np.ndarray] | None = None


class StereoDataset(Sequence[StereoSample]):
    """The samples of one dataset, read from disk on ``__getitem__`` (nothing is cached)."""

    def __init__(self, root: Path, layout: str, files: Sequence[SampleFiles]) -> None:
        self.root = root
        self.layout = layout
        self.files = tuple(files)

    def __len__(self) -> int:
        return len(self.files)

    @overload
    def __getitem__(self, index: int) -> StereoSample: ...

    @overload
    def __getitem__(self, index: slice) -> StereoDataset: ...

    def __getitem__(self, index: int | slice) -> StereoSample | StereoDataset:
        if isinstance(index, slice):
            return StereoDataset(self.root, self.layout, self.files[index])
        return _load(self.files[index], LAYOUTS[self.layout])

    def __iter__(self) -> Iterator[StereoSample]:
        for index in range(len(self)):
            yield self[index]

    def __repr__(self) -> str:
        return f"StereoDataset(root={str(self.root)!r}, layout={self.layout!r}, samples={len(self)})"


def _load(files: SampleFiles, layout: _Layout) -> StereoSample:
    left, right = read_image(files.left), read_image(files.right)
    disparity = layout.read_disparity(files.disparity)
    if disparity.ndim != 2:
        raise FormatError(f"{str(files.disparity)!r}: disparity must be HxW, got {disparity.shape}")
    nonoccluded = None
    if files.nonoccluded is not None and layout.read_nonoccluded is not None:
        nonoccluded = layout.read_nonoccluded(files.nonoccluded)
    shapes = {left.shape[:2], right.shape[:2], disparity.shape}
    if nonoccluded is not None:
        shapes.add(nonoccluded.shape)
    if len(shapes) != 1:
        raise FormatError(f"sample {files.name!r}: images and ground truth differ in size {shapes}")
    disparity[~np.isfinite(disparity)] = np.inf  # nan also means unknown
    valid = np.isfinite(disparity)
    if nonoccluded is not None:
        nonoccluded &= valid
    return StereoSample(files.name, left, right, disparity, valid, nonoccluded)


def _read_nonoccluded_mask(path: Path) -> np.ndarray:
    """Middlebury / ETH3D ``mask0nocc.png``: 255 = non-occluded (128 = occluded, 0 = unknown)."""
    mask: np.ndarray = read_image(path, gray_to_rgb=False) == 255
    return mask


def _read_kitti_nonoccluded(path: Path) -> np.ndarray:
    """KITTI ``disp_noc``: the pixels with ground truth there are the non-occluded ones."""
    known: np.ndarray = np.isfinite(read_kitti_disparity(path))
    return known


def _optional(path: Path) -> Path | None:
    return path if path.is_file() else None


def _scene_folder_finder(grayscale: bool) -> Callable[[Path], list[SampleFiles]]:
    """Middlebury 2014 (colour) / ETH3D (grayscale): one folder per scene holding im0, im1,
    disp0GT, mask0nocc. The two are told apart by the colour type in ``im0.png``'s header."""

    def find(root: Path) -> list[SampleFiles]:
        return [files for files in _find_scene_folders(root) if _is_grayscale_png(files.left) == grayscale]

    return find


def _find_scene_folders(root: Path) -> list[SampleFiles]:
    return [
        SampleFiles(
            name=scene.name,
            left=scene / "im0.png",
            right=scene / "im1.png",
            disparity=scene / "disp0GT.pfm",
            nonoccluded=_optional(scene / "mask0nocc.png"),
        )
        for scene in sorted(path.parent for path in root.glob("*/disp0GT.pfm"))
        if (scene / "im0.png").is_file() and (scene / "im1.png").is_file()
    ]


def _kitti_finder(left: str, right: str, disparity: str, nonoccluded: str) -> Callable[[Path], list[SampleFiles]]:
    """KITTI: parallel folders of ``NNNNNN_10.png`` files (frame 10 is the one with ground truth)."""

    def find(root: Path) -> list[SampleFiles]:
        if not (root / disparity).is_dir() and (root / "training" / disparity).is_dir():
            root = root / "training"
        return [
            SampleFiles(
                name=gt.stem,
                left=root / left / gt.name,
                right=root / right / gt.name,
                disparity=gt,
                nonoccluded=_optional(root / nonoccluded / gt.name),
            )
            for gt in sorted((root / disparity).glob("*_10.png"))
            if (root / left / gt.name).is_file() and (root / right / gt.name).is_file()
        ]

    return find


def _find_sceneflow(root: Path) -> list[SampleFiles]:
    """SceneFlow: ``disparity/<rel>/left/N.pfm`` with ``frames_cleanpass/<rel>/{left,right}/N.png``.

    The clean pass is used when present, else the final pass. ``<rel>`` is any nesting
    (``TRAIN/A/0000``, ``15mm_focallength/scene_forwards/fast``, ``a_rain_of_stones_x2``, ...).
    """
    if not (root / "disparity").is_dir():
        return []
    frames = next(
        (root / name for name in ("frames_cleanpass", "frames_finalpass") if (root / name).is_dir()),
        None,
    )
    if frames is None:
        return []
    samples = []
    for gt in sorted((root / "disparity").rglob("left/*.pfm")):
        sequence = gt.parent.parent.relative_to(root / "disparity")
        left = frames / sequence / "left" / f"{gt.stem}.png"
        right = frames / sequence / "right" / f"{gt.stem}.png"
        if left.is_file() and right.is_file():
            samples.append(SampleFiles(f"{sequence.as_posix()}/{gt.stem}", left, right, gt))
    return samples


def _find_simple(root: Path) -> list[SampleFiles]:
    """One folder per pair: ``NAME/{left.png, right.png, disp.pfm}``."""
    return [
        SampleFiles(folder.name, folder / "left.png", folder / "right.png", folder / "disp.pfm")
        for folder in sorted(path.parent for path in root.glob("*/disp.pfm"))
        if (folder / "left.png").is_file() and (folder / "right.png").is_file()
    ]


LAYOUTS: dict[str, _Layout] = {
    "middlebury2014": _Layout(_scene_folder_finder(False), read_pfm, _read_nonoccluded_mask),
    "eth3d": _Layout(_scene_folder_finder(True), read_pfm, _read_nonoccluded_mask),
    "kitti2012": _Layout(
        _kitti_finder("colored_0", "colored_1", "disp_occ", "disp_noc"),
        read_kitti_disparity,
        _read_kitti_nonoccluded,
    ),
    "kitti2015": _Layout(
        _kitti_finder("image_2", "image_3", "disp_occ_0", "disp_noc_0"),
        read_kitti_disparity,
        _read_kitti_nonoccluded,
    ),
    "sceneflow": _Layout(_find_sceneflow, read_pfm),
    "simple": _Layout(_find_simple, read_pfm),
}
"""Layout name -> layout. Auto-detection tries them in this order."""


def open_dataset(root: str | os.PathLike[str], layout: str = "auto") -> StereoDataset:
    """Open the dataset under ``root``; ``layout`` is a name from :data:`LAYOUTS` or ``"auto"``.

    Listing checks that each sample's files exist; the files are read only on ``ds[i]``.
    Raises FormatError when ``root`` is not a folder, the layout is unknown, or no sample is found.
    """
    root = Path(root)
    if not root.is_dir():
        raise FormatError(f"dataset root {str(root)!r} is not a folder")
    supported = ", ".join(LAYOUTS)
    if layout != "auto":
        if layout not in LAYOUTS:
            raise FormatError(f"unknown layout {layout!r}; supported: {supported}, auto")
        files = LAYOUTS[layout].find(root)
        if not files:
            raise FormatError(f"no {layout} samples under {str(root)!r}")
        return StereoDataset(root, layout, files)
    for name, candidate in LAYOUTS.items():
        files = candidate.find(root)
        if files:
            return StereoDataset(root, name, files)
    raise FormatError(
        f"no known stereo dataset layout under {str(root)!r}; supported layouts: {supported} "
        "(see stereo_data.readers for the expected files)"
    )


def _is_grayscale_png(path: Path) -> bool:
    """True when ``path`` is a PNG whose header declares a grayscale colour type (0, or 4: with
    alpha); False for colour PNGs and anything else."""
    with path.open("rb") as file:
        header = file.read(26)
    return len(header) == 26 and header[:8] == b"\x89PNG\r\n\x1a\n" and header[25] in (0, 4)
