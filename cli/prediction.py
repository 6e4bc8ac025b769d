"""What `crestereo-pp predict` does: find the pairs, compute them, write their outputs."""

from __future__ import annotations

import argparse
import glob
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import ExitStack, closing
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple, Protocol

import cv2
import numpy as np
from tqdm import tqdm

from crestereo_pp.inference import InferenceOptions, RowOffset, parse_iterations
from crestereo_pp.inference.row_alignment import align_rows
from crestereo_pp.stereo_data.formats import (
    encode_png,
    read_image,
    write_depth,
    write_depth_mm,
    write_disparity,
    write_uncertainty,
)
from crestereo_pp.stereo_data.output_maps import OutputOptions, PredictionOutputs
from crestereo_pp.stereo_data.pointcloud import DepthRange, FocalBaseline
from crestereo_pp.stereo_data.rig import Rectifier, focal_baseline_problem, read_rig
from crestereo_pp.stereo_data.visualize import color_scale_problem, disparity_picture

from .options import inference_options, load_predictor

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v"}


@dataclass(frozen=True)
class PairPaths:
    """Input images of one pair and the output `stem` (relative path without extension)."""

    left: Path
    right: Path
    stem: Path


def is_single_pair(left: str, right: str) -> bool:
    """True when LEFT and RIGHT name two image files (then OUT names a file, not a folder)."""
    return Path(left).is_file() and Path(right).is_file() and not is_video_pair(left, right)


def is_video_pair(left: str, right: str) -> bool:
    """True when LEFT and RIGHT name two video files (a stereo video, frame by frame)."""
    return all(Path(name).is_file() and Path(name).suffix.lower() in VIDEO_SUFFIXES for name in (left, right))


@dataclass(frozen=True)
class PairImages:
    """One pair to compute: where it comes from (the output stem) and its images, RGB."""

    pair: PairPaths
    left: np.ndarray
    right: np.ndarray


def read_frames(job: Job) -> tuple[int, Iterator[PairImages]]:
    """How many pairs the job computes (a video's count is its container's estimate) and the
    pairs themselves, read one at a time."""
    if job.pairs is None:
        return video_frames(Path(job.args.left), Path(job.args.right))
    return len(job.pairs), (PairImages(pair, *read_pair(pair)) for pair in job.pairs)


def read_pair(pair: PairPaths) -> tuple[np.ndarray, np.ndarray]:
    left, right = read_image(pair.left), read_image(pair.right)
    if left.shape != right.shape:
        sizes = [
            f"{path} is {image.shape[1]}x{image.shape[0]}" for path, image in ((pair.left, left), (pair.right, right))
        ]
        raise ValueError(f"{sizes[0]} but {sizes[1]}: a stereo pair has two images of one size")
    return left, right


def video_frames(left: Path, right: Path) -> tuple[int, Iterator[PairImages]]:
    """The frames of two videos of one stereo camera, in lockstep (ValueError where they cannot
    be read or hold different numbers of frames)."""
    videos = [cv2.VideoCapture(str(path)) for path in (left, right)]
    for path, video in zip((left, right), videos, strict=True):
        if not video.isOpened():
            raise ValueError(f"{path}: not a video that OpenCV can read")
    counts = [int(video.get(cv2.CAP_PROP_FRAME_COUNT)) for video in videos]
    if counts[0] != counts[1]:
        raise ValueError(f"{left} has {counts[0]} frames but {right} has {counts[1]}: a stereo video has one count")

    def frames() -> Iterator[PairImages]:
        try:
            for index in range(counts[0]):
                read = [video.read() for video in videos]
                if not all(ok for ok, _ in read):
                    return  # the containers over-counted: what was read is what there is
                images = [cv2.cvtColor(image, cv2.COLOR_BGR2RGB) for _, image in read]
                yield PairImages(PairPaths(left, right, Path(f"frame_{index:06d}")), images[0], images[1])
        finally:
            for video in videos:
                video.release()

    return counts[0], frames()


GLOB_CHARACTERS = frozenset("*?[")


def _input_kind(name: str) -> str:
    """What LEFT or RIGHT names: a file, a folder, a glob (a name with glob characters that is
    neither), or nothing."""
    path = Path(name)
    if path.is_file():
        return "file"
    if path.is_dir():
        return "folder"
    return "glob" if GLOB_CHARACTERS & set(name) else "missing"


def check_inputs(left: str, right: str) -> None:
    """Refuse, before anything is loaded, inputs that name nothing or two different kinds of
    thing (a file and a folder, say): ValueError naming what was wrong."""
    kinds = {name: _input_kind(name) for name in (left, right)}
    for name, kind in kinds.items():
        if kind == "missing":
            raise ValueError(f"{name}: no such file or folder")
    if kinds[left] != kinds[right]:
        raise ValueError(
            f"LEFT {left} is a {kinds[left]} but RIGHT {right} is a {kinds[right]}: give two image or video files, "
            "two folders, or two quoted globs"
        )


def find_pairs(left: str, right: str) -> list[PairPaths]:
    """Pairs named by LEFT and RIGHT: two files, two folders (matched by file name), or two globs
    (matched in sorted order). Stems are relative to the folder holding all left images."""
    if is_single_pair(left, right):
        return [PairPaths(Path(left), Path(right), Path(Path(left).stem))]
    if Path(left).is_dir() and Path(right).is_dir():
        lefts = {p.name: p for p in Path(left).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        rights = {p.name: p for p in Path(right).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
        if not lefts:
            raise ValueError(f"{left}: no images in the folder (files ending in {', '.join(sorted(IMAGE_SUFFIXES))})")
        if set(lefts) != set(rights):
            unmatched = sorted(set(lefts) ^ set(rights))
            raise ValueError(f"{len(unmatched)} image(s) have no partner in the other folder: {unmatched[:5]}")
        return _unique_stems([PairPaths(lefts[name], rights[name], Path(lefts[name].stem)) for name in sorted(lefts)])
    left_paths = [Path(p) for p in sorted(glob.glob(left)) if Path(p).is_file()]
    right_paths = [Path(p) for p in sorted(glob.glob(right)) if Path(p).is_file()]
    if not left_paths:
        raise ValueError(f"no left image matches {left!r}")
    if len(left_paths) != len(right_paths):
        raise ValueError(
            f"{len(left_paths)} left images match {left!r} but {len(right_paths)} right images match {right!r}"
        )
    root = Path(os.path.commonpath([p.parent.resolve() for p in left_paths]))
    return _unique_stems(
        [
            PairPaths(left_path, right_path, left_path.resolve().relative_to(root).with_suffix(""))
            for left_path, right_path in zip(left_paths, right_paths, strict=True)
        ]
    )


def _unique_stems(pairs: list[PairPaths]) -> list[PairPaths]:
    """`pairs`, once no two share a stem (x.png and x.jpg would write one x.pfm, the second pair's
    over the first's): ValueError naming two that do."""
    seen: dict[Path, Path] = {}
    for pair in pairs:
        if pair.stem in seen:
            raise ValueError(
                f"{seen[pair.stem]} and {pair.left} would write their outputs to one name ({pair.stem}): "
                "rename one, or compute them apart"
            )
        seen[pair.stem] = pair.left
    return pairs


@dataclass(frozen=True)
class Output:
    """One output option: its flag, the path given, what is written there and the suffixes it takes
    (the first is the one of folder mode)."""

    flag: str
    path: Path
    what: str
    suffixes: tuple[str, ...]

    def file(self, pair: PairPaths, single: bool) -> Path:
        return self.path if single else self.path / f"{pair.stem}{self.suffixes[0]}"


def outputs(args: argparse.Namespace) -> list[Output]:
    """The outputs asked for, disparity first."""
    maps = (".pfm", ".png", ".npy")
    disparity_suffixes = (f".{args.format}", *(s for s in maps if s != f".{args.format}"))
    candidates = [
        Output("--output", args.output, "disparity", disparity_suffixes),
        Output("--uncertainty", args.uncertainty, "uncertainty", maps),
        Output("--depth", args.depth, "depth", maps),
        Output("--depth-mm", args.depth_mm, "depth in mm", (".png",)),
        Output("--color", args.color, "colour picture", (".png",)),
        Output("--ply", args.ply, "point cloud", (".ply",)),
    ]
    return [output for output in candidates if output.path is not None]


def check_outputs(targets: list[Output], single: bool, mkdir: bool) -> None:
    """Refuse, before anything is computed, an output that could not be written: a file name
    without a suffix of its kind or that names a folder, a folder that is a file, a missing folder
    (unless `mkdir`), or a path that another output names too."""
    named: dict[Path, str] = {}
    for output in targets:
        other = named.setdefault(output.path.resolve(), output.flag)
        if other != output.flag:
            raise ValueError(f"{output.flag} {output.path}: {other} names it too; each output needs a path of its own")
        if single and output.path.suffix.lower() not in output.suffixes:
            raise ValueError(f"{output.flag} {output.path}: the file name must end in {', '.join(output.suffixes)}")
        if single and output.path.is_dir():
            raise ValueError(f"{output.flag} {output.path}: is a folder; with one pair it names a file")
        if not single and output.path.exists() and not output.path.is_dir():
            raise ValueError(f"{output.flag} {output.path}: is a file; with several pairs it names a folder")
        folder = output.path.parent if single else output.path
        if not folder.is_dir() and not mkdir:
            raise ValueError(
                f"{output.flag} {output.path}: the folder {folder} does not exist (create it, or add --mkdir)"
            )


class OutputOption(NamedTuple):
    """An option that shapes some outputs only: given without one of them it is refused, as a
    mistake, rather than ignored."""

    flag: str
    given: Callable[[argparse.Namespace], bool]
    needs: str  # the outputs it shapes, as the message names them
    needed: Callable[[argparse.Namespace], bool]  # whether one of them is asked for


def _asked(*names: str) -> Callable[[argparse.Namespace], bool]:
    """Whether any of the arguments `names` was given."""
    return lambda args: any(getattr(args, name) is not None for name in names)


OUTPUT_OPTIONS = (
    OutputOption("--color-min", _asked("color_min"), "--color", _asked("color")),
    OutputOption("--color-max", _asked("color_max"), "--color", _asked("color")),
    OutputOption("--cx", _asked("cx"), "--ply", _asked("ply")),
    OutputOption("--cy", _asked("cy"), "--ply", _asked("ply")),
    OutputOption("--max-uncertainty", _asked("max_uncertainty"), "--ply", _asked("ply")),
    OutputOption(
        "--max-depth-m", _asked("max_depth_m"), "--depth, --depth-mm or --ply", _asked("depth", "depth_mm", "ply")
    ),
)

LOCAL_MODEL_FLAGS: dict[str, Callable[[argparse.Namespace], bool]] = {
    "--weights": lambda args: args.weights is not None,
    "--device": lambda args: args.device != "auto",
    "--backend": lambda args: args.backend != "auto",
    "--precision": lambda args: args.precision != "auto",
}
"""The options that choose how a model here computes (none applies to a service's, `--url`)."""


@dataclass(frozen=True)
class Job:
    """What the command computes for each pair and where it writes it (from its arguments)."""

    args: argparse.Namespace
    targets: list[Output]
    single: bool
    outputs: OutputOptions  # its rectifier, where the pairs are raw, rectifies them first
    pairs: list[PairPaths] | None  # the image pairs LEFT and RIGHT name (None: two videos)


def plan(args: argparse.Namespace) -> Job:
    """The job the arguments describe; ValueError, before any model is loaded, where they are
    inconsistent, an input names nothing, or an output could not be written."""
    check_inputs(args.left, args.right)
    if (args.focal_px is None) != (args.baseline_m is None):
        raise ValueError("give both --focal-px and --baseline-m, or neither")
    if args.focal_px is not None:
        problem = focal_baseline_problem(args.focal_px, args.baseline_m, "--focal-px x --baseline-m")
        if problem is not None:
            raise ValueError(problem)
    if args.calibration is not None and args.focal_px is not None:
        raise ValueError("--calibration gives the focal length and baseline: leave out --focal-px and --baseline-m")
    if args.frame == "original" and args.calibration is None:
        raise ValueError("--frame original needs --calibration (a rectified pair has no other frame)")
    for flag, path in (("--depth", args.depth), ("--depth-mm", args.depth_mm)):
        if path is not None and args.focal_px is None and args.calibration is None:
            raise ValueError(f"{flag} needs --calibration, or --focal-px and --baseline-m")
    if args.warm_iters is not None and not args.sequence:
        raise ValueError("--warm-iters needs --sequence (only a sequence's frames start warm)")
    for option in OUTPUT_OPTIONS:
        if option.given(args) and not option.needed(args):
            raise ValueError(f"{option.flag} applies only with {option.needs}: without it, it would change nothing")
    problem = color_scale_problem(args.color_min, args.color_max, ("--color-min", "--color-max"))
    if problem is not None:
        raise ValueError(problem)
    if args.url is not None:
        from crestereo_pp.client import service_address

        try:
            service_address(args.url)
        except ValueError as error:
            raise ValueError(f"--url {error}") from None
        chosen_here = [flag for flag, given in LOCAL_MODEL_FLAGS.items() if given(args)]
        if chosen_here or args.ray:
            flags = ", ".join([*chosen_here, *(["--ray"] if args.ray else [])])
            raise ValueError(f"{flags}: with --url the service computes the pairs, with its own model")
    rectifier = None if args.calibration is None else Rectifier(read_rig(args.calibration))
    single = is_single_pair(args.left, args.right)
    targets = outputs(args)
    check_outputs(targets, single, args.mkdir)
    pairs = None if is_video_pair(args.left, args.right) else find_pairs(args.left, args.right)
    if pairs is not None:
        check_inputs_kept(targets, pairs, single)
    focal_baseline = (
        rectifier.focal_baseline
        if rectifier is not None
        else None
        if args.focal_px is None
        else FocalBaseline(args.focal_px, args.baseline_m, args.cx, args.cy)
    )
    options = OutputOptions(
        focal_baseline=focal_baseline,
        limits=DepthRange(args.min_disparity, args.max_depth_m),
        rectifier=rectifier,
        original=args.frame == "original",
        color_min=args.color_min,
        color_max=args.color_max,
        max_uncertainty=args.max_uncertainty,
    )
    return Job(args, targets, single, options, pairs)


def check_inputs_kept(targets: list[Output], pairs: list[PairPaths], single: bool) -> None:
    """Refuse, before anything is computed, an output file that would replace one of the input
    images (`-o left.png`, or a folder of outputs written over its images)."""
    inputs = {path.resolve() for pair in pairs for path in (pair.left, pair.right)}
    for pair in pairs:
        for output in targets:
            path = output.file(pair, single)
            if path.resolve() in inputs:
                raise ValueError(f"{output.flag} {output.path}: would write over the input image {path}")


def is_complete(job: Job, pair: PairPaths) -> bool:
    """Whether every output of `pair` exists (each is written whole or not at all)."""
    return all(output.file(pair, job.single).is_file() for output in job.targets)


class ComputedMaps(Protocol):
    """A pair's maps: disparity (float32 HxW, px of the left image) and uncertainty (float32 HxW)."""

    @property
    def disparity(self) -> np.ndarray: ...

    @property
    def uncertainty(self) -> np.ndarray: ...


class Frames(Protocol):
    """What computes a job's pairs one after the other: a model here (`FrameStream`), or a running
    service (`cli.service_frames.ServiceFrames`, with --url)."""

    def predict(self, left: np.ndarray, right: np.ndarray) -> ComputedMaps: ...

    def restart(self) -> None: ...


def predict_and_write(job: Job, stream: Frames, images: PairImages) -> RowOffset | None:
    """Compute one pair (rectified first where the job has a calibration; warm-started from the
    stream's previous pair only with --sequence) and write its outputs, each to a temporary name
    first and then renamed: an interrupted run leaves no partial file. With --align-rows (the
    default) the right image is put onto the left's rows here, once (`inference.align_rows`), and
    the frames compute the pair so (`frame_options`); returns how far its rows lay off (None where
    not measured, or too bare to measure)."""
    args, pair, left, right = job.args, images.pair, images.left, images.right
    if not args.sequence:
        stream.restart()  # every pair on its own
    rectifier = job.outputs.rectifier
    if rectifier is not None:
        left, right = rectifier.rectify(left, right)  # refuses a pair of another size than the calibration's
        if job.single:
            print(describe_camera(rectifier.focal_baseline))
    offset = None
    if args.align_rows:
        right, offset = align_rows(left, right)
        if job.single:
            print(describe_rows(offset))
    prediction = stream.predict(left, right)
    outputs = PredictionOutputs(prediction.disparity, prediction.uncertainty, left, job.outputs)
    disparity, uncertainty, depth = outputs.maps
    for output in job.targets:
        path = output.file(pair, job.single)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.stem}.partial{path.suffix}")
        try:
            if output.flag == "--output":
                write_disparity(partial, disparity)
            elif output.flag == "--uncertainty":
                write_uncertainty(partial, uncertainty)
            elif output.flag in ("--depth", "--depth-mm"):
                assert depth is not None  # checked in plan()
                (write_depth if output.flag == "--depth" else write_depth_mm)(partial, depth)
            elif output.flag == "--color":
                partial.write_bytes(encode_png(disparity_picture(*outputs.colored_disparity())))
            else:  # points in the (rectified) left camera's frame, coloured by the image the network saw
                partial.write_bytes(outputs.ply())
            os.replace(partial, path)
        except BaseException:  # a failed write or Ctrl-C: no partial file stays behind
            partial.unlink(missing_ok=True)
            raise
        if job.single:
            print(f"wrote {output.what} {path}")
    return offset


OFF_ROWS_PX = 1.0
"""Rows off by this much (px) somewhere say that the rig's calibration is off."""


def describe_off_rows(largest_px: list[float], pairs: int) -> str:
    """The line that counts the pairs of a run whose right rows lay OFF_ROWS_PX or more off the
    left's (`largest_px`: each such pair's largest offset) among the `pairs` computed."""
    return (
        f"rows: the right image's lay {OFF_ROWS_PX:g} px or more off the left's in {len(largest_px)} of {pairs} "
        f"pairs (up to {max(largest_px):.2f} px), aligned before matching; check the rig's calibration"
    )


def describe_rows(offset: RowOffset | None) -> str:
    """The line that says how far a pair's right rows lay off the left's (`measure_row_offset`)."""
    if offset is None:
        return "rows: too little texture to measure the right image's offset from the left's"
    if not offset.aligned:
        return f"rows: the right image's lie on the left's (within {offset.largest_px:.2f} px)"
    advice = "; check the rig's calibration" if offset.largest_px >= OFF_ROWS_PX else ""
    return (
        f"rows: the right image's lay up to {offset.largest_px:.2f} px off the left's ({offset.centre_px:+.2f} px at "
        f"the centre, {offset.across_px:+.2f} across, {offset.down_px:+.2f} down), aligned before matching{advice}"
    )


def describe_camera(camera: FocalBaseline) -> str:
    """The line that says which rectified camera a calibration gave (depth = focal x baseline / disparity)."""
    assert camera.cx is not None and camera.cy is not None  # a rig always has its principal point
    return (
        f"rectified camera: focal length {camera.focal_px:.2f} px, baseline {camera.baseline_m:.4f} m, "
        f"principal point ({camera.cx:.2f}, {camera.cy:.2f}) px"
    )


def prepare(args: argparse.Namespace) -> Job:
    """The job the arguments describe (`plan`); where its pairs are raw, the rectified camera
    its depth comes from is printed: first for a run over several pairs, and for a single pair
    once it is rectified (`predict_and_write`: not before the refusal of a pair of another size)."""
    job = plan(args)
    if job.outputs.rectifier is not None and not job.single:
        print(describe_camera(job.outputs.rectifier.focal_baseline))
    return job


def run(job: Job) -> int:
    """Compute the job's pairs one after the other (a sequence's each from the previous one), here
    or, with --url, on a running service."""
    args = job.args
    if args.address is not None or args.workers is not None:
        raise ValueError("--address and --workers only apply with --ray")
    count, frames = read_frames(job)
    written, off_rows = 0, []
    with ExitStack() as resources:
        stream = frames_of(job, resources)
        try:
            for images in tqdm(frames, total=count, desc=f"predict {args.model}", unit="pair", disable=job.single):
                offset = predict_and_write(job, stream, images)
                if offset is not None and offset.largest_px >= OFF_ROWS_PX:
                    off_rows.append(offset.largest_px)
                written += 1
        except KeyboardInterrupt:
            print(f"{written} of {count} pair(s) written before the interrupt, each whole", file=sys.stderr)
            raise
    if not job.single:  # every output was written once per pair (any failure stops the command)
        for output in job.targets:
            print(f"wrote {written} {output.what} files to {output.path}")
        if off_rows:
            print(describe_off_rows(off_rows, written))
    return 0


def frames_of(job: Job, resources: ExitStack) -> Frames:
    """What computes the job's pairs: with --url the service there (its connection closed with
    `resources`), else the model the options name, loaded here."""
    args = job.args
    if args.url is not None:
        from .service_frames import ServiceFrames

        service = ServiceFrames(args.url, args.api_key, args.model, frame_options(args), args.sequence, args.warm_iters)
        return resources.enter_context(closing(service))
    return load_predictor(args).stream(frame_options(args), parse_iterations(args.warm_iters))


def frame_options(args: argparse.Namespace) -> InferenceOptions:
    """The command's options as its frames compute each pair: the rows already aligned, where asked,
    by `predict_and_write` (so that they are measured once, here or with --url, not again there)."""
    return replace(inference_options(args), align_rows=False)
