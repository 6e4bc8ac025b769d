"""Spec of the OpenVINO backend: the same maps as torch for every knob, never a stalled call, a
disk cache that spares a restart the export, and an honest choice of backend and precision.

The graphs here run one iteration per stage: an export costs CPU time in proportion to the
iterations it unrolls, and the equality of the maps does not depend on their number.
"""

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from model import load_model
from model.inference import resolve_backend, resolve_precision
from model.openvino_backend import native_bf16
from shared_data import STEREO_DEV

ITERS = (1, 1, 1)
PAIR = STEREO_DEV / "middlebury2001_tsukuba"  # 384x288, the smallest real pair


@pytest.fixture(scope="module")
def tsukuba():
    if not PAIR.is_dir():
        pytest.skip(f"the real pairs are not at {STEREO_DEV}")
    left, right = (cv2.imread(str(PAIR / name))[..., ::-1].copy() for name in ("left.png", "right.png"))
    return left, right


@pytest.fixture(scope="module")
def cache_dir(openvino_cache):
    return openvino_cache


@pytest.fixture(scope="module")
def torch_lite():
    return load_model("lite", backend="torch")


class Messages(logging.Handler):
    """The messages logged to one logger while attached."""

    def __init__(self) -> None:
        super().__init__(level=logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture(scope="module")
def first_call(cache_dir, tsukuba):
    """An OpenVINO predictor with an empty cache: its first call (before any graph exists) and what
    it logged, then the graphs for cold and warm starts made ready."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
        predictor = load_model("lite", backend="openvino", precision="fp32")
    logger, messages = logging.getLogger("model.openvino_backend"), Messages()
    logger.addHandler(messages)
    logger.setLevel(logging.INFO)
    try:
        before = predictor.predict(*tsukuba, iters=ITERS)
    finally:
        logger.removeHandler(messages)
        logger.setLevel(logging.NOTSET)
    counts = (predictor.openvino.runs, predictor.openvino.fallback_runs)
    assert predictor.prepare(ITERS) and predictor.prepare(ITERS, warm_start=True)
    return predictor, before, "\n".join(messages.messages), counts


def assert_maps_agree(actual, expected) -> None:
    """OpenVINO f32 against torch: float rounding only (0.0004 px seen at most on real pairs)."""
    for name in ("disparity", "uncertainty"):
        a, e = (np.asarray(getattr(maps, name), np.float64) for maps in (actual, expected))
        assert a.shape == e.shape
        assert np.abs(a - e).max() < 0.01, (name, np.abs(a - e).max())


def test_a_graph_not_ready_yet_runs_on_torch_while_it_is_exported_in_the_background(first_call, torch_lite, tsukuba):
    predictor, before, log, (runs, fallback_runs) = first_call
    assert (runs, fallback_runs) == (0, 2)  # nothing waited for the export: auto's quick pass, then the pass
    expected = torch_lite.predict(*tsukuba, iters=ITERS)
    np.testing.assert_array_equal(before.disparity, expected.disparity)  # torch itself computed it
    assert "exporting the graph for iterations (1, 1, 1)" in log and "run on torch until it is ready" in log


def test_openvino_maps_equal_torch_maps_on_a_real_pair_for_every_knob(first_call, torch_lite, tsukuba):
    predictor, *_ = first_call
    left, right = tsukuba
    runs = predictor.openvino.runs
    for options in (
        {},
        {"two_pass": True},
        {"two_pass": False},
        {"scale": 0.5},
        {"raw_uncertainty": True},
        {"init_disparity": torch_lite.predict(left, right, iters=ITERS).disparity},
    ):
        assert_maps_agree(
            predictor.predict(left, right, iters=ITERS, **options),
            torch_lite.predict(left, right, iters=ITERS, **options),
        )
    # A batch of two sizes, padded to one shape as torch pads it.
    lefts, rights = [left, left[:200, :300]], [right, right[:200, :300]]
    for actual, expected in zip(
        predictor.predict_batch(lefts, rights, iters=ITERS, two_pass=False),
        torch_lite.predict_batch(lefts, rights, iters=ITERS, two_pass=False),
        strict=True,
    ):
        assert_maps_agree(actual, expected)
    # auto (the default) runs a quick pass first, two_pass=True a half-resolution one, a warm start one
    # pass; at scale 0.5 (144 x 192 px) auto takes one pass without a quick one
    assert predictor.openvino.runs - runs == 2 + 2 + 1 + 1 + 2 + 1 + 1 and predictor.openvino.fallback_runs == 2


def test_a_restart_reads_its_graphs_from_the_disk_cache_without_exporting(first_call, cache_dir, tsukuba):
    assert any(cache_dir.rglob("*.xml")) and any((cache_dir / "openvino" / "compiled").iterdir())
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
        restarted = load_model("lite", backend="openvino", precision="fp32")
    restarted.predict(*tsukuba, iters=ITERS)
    # auto's quick pass and the pass, both compiled from the cache
    assert (restarted.openvino.runs, restarted.openvino.fallback_runs, restarted.openvino.exports) == (2, 0, 0)


def test_compiled_shapes_are_kept_up_to_a_bound_least_recently_used_first(first_call, tsukuba):
    predictor, *_ = first_call
    backend = predictor.openvino
    backend.max_shapes = 2
    left, right = tsukuba
    for height in (64, 96, 128):  # three padded shapes
        predictor.predict(left[:height, :128], right[:height, :128], iters=ITERS, two_pass=False)
    assert len(backend.compiled) == 2
    assert [key[1][2] for key in backend.compiled] == [96, 128]


def test_bf16_moves_the_maps_a_little_and_runs_only_where_asked(first_call, tsukuba):
    predictor, *_ = first_call
    fp32 = predictor.predict(*tsukuba, iters=ITERS)
    predictor.precision = "bf16"
    try:
        bf16 = predictor.predict(*tsukuba, iters=ITERS)
    finally:
        predictor.precision = "fp32"
    difference = np.abs(bf16.disparity - fp32.disparity)
    assert 0 < difference.mean() < 0.5, difference.mean()


def test_auto_picks_openvino_on_a_cpu_and_bf16_only_where_the_cpu_computes_it(tmp_path: Path, monkeypatch):
    monkeypatch.delenv("CRESTEREO_BACKEND")
    cpu = torch.device("cpu")
    assert resolve_backend("auto", cpu) == "openvino"
    assert resolve_backend("auto", torch.device("meta")) == "torch"
    monkeypatch.setenv("CRESTEREO_BACKEND", "torch")
    assert resolve_backend("auto", cpu) == "torch"
    with pytest.raises(ValueError, match="runs on the CPU"):
        resolve_backend("openvino", torch.device("meta"))
    monkeypatch.setenv("CRESTEREO_BACKEND", "tensorrt")
    with pytest.raises(ValueError, match="unknown backend"):
        resolve_backend("auto", cpu)

    flags = tmp_path / "cpuinfo"
    flags.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f\n")
    assert not native_bf16(flags)
    flags.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16\n")
    assert native_bf16(flags)
    assert not native_bf16(tmp_path / "missing")
    assert resolve_precision("auto", "torch") == "fp32"
    assert resolve_precision("bf16", "torch") == "bf16"
    assert resolve_precision("auto", "openvino") == ("bf16" if native_bf16() else "fp32")
