"""crestereo_pp.inference.cuda_graphs: which calls capture, replay or run eagerly, what the static buffers hold, the
cache bound and the fallback, on the CPU with a capture that replays eagerly; then the real
capture, on CUDA only."""

import warnings

import numpy as np
import pytest
import torch

from crestereo_pp.inference import load_model
from crestereo_pp.inference.cuda_graphs import GraphedForward, GraphKey, capture_cuda_graph
from fake_accelerator import replay_eagerly

ITERS = (1, 1, 2)
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


class RecordingForward:
    """A cheap stand-in for StereoPredictor.forward: maps that depend on every input, and a count
    of the calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, left, right, init, iters, bf16):
        self.calls += 1
        disparity = (left - right).mean(1, keepdim=True) * iters[2] + (0.0 if init is None else init)
        return disparity, right[:, :1] * (2.0 if bf16 else 1.0)


def images(seed: int, shape=(1, 3, 32, 64)) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=generator) * 255, torch.rand(shape, generator=generator) * 255


def graphed(**options) -> tuple[GraphedForward, RecordingForward]:
    forward = RecordingForward()
    return GraphedForward(forward, capture=replay_eagerly, **options), forward


def test_a_key_runs_eagerly_first_then_is_captured_once_and_replayed():
    runner, _ = graphed(capture_after=2)
    left, right = images(0)
    for _ in range(4):
        runner(left, right, None, ITERS, False)
    assert (runner.eager_runs, runner.captures, runner.replays) == (1, 1, 3)
    assert list(runner.graphs) == [GraphKey((1, 3, 32, 64), False, ITERS, False)]


def test_a_replay_computes_on_the_new_inputs_and_earlier_results_stay_valid():
    runner, forward = graphed(capture_after=1)
    first_left, first_right = images(1)
    second_left, second_right = images(2)
    first = runner(first_left, first_right, None, ITERS, False)
    second = runner(second_left, second_right, None, ITERS, False)
    assert runner.replays == 2 and runner.captures == 1
    for result, (left, right) in ((first, (first_left, first_right)), (second, (second_left, second_right))):
        expected = forward(left, right, None, ITERS, False)
        for got, want in zip(result, expected, strict=True):
            torch.testing.assert_close(got, want)


def test_the_warm_start_is_copied_into_its_buffer_too():
    runner, forward = graphed(capture_after=1)
    left, right = images(3)
    for value in (1.0, 5.0):
        init = torch.full((1, 1, 32, 64), value)
        disparity, _ = runner(left, right, init, ITERS, False)
        torch.testing.assert_close(disparity, forward(left, right, init, ITERS, False)[0])


@pytest.mark.parametrize(
    "change",
    [
        dict(shape=(2, 3, 32, 64)),
        dict(shape=(1, 3, 64, 64)),
        dict(iters=(1, 1, 3)),
        dict(bf16=True),
        dict(init=True),
    ],
    ids=["batch", "size", "iters", "bf16", "warm-start"],
)
def test_every_part_of_the_key_gets_a_graph_of_its_own(change):
    runner, _ = graphed(capture_after=1)
    left, right = images(4)
    runner(left, right, None, ITERS, False)
    left, right = images(5, change.get("shape", (1, 3, 32, 64)))
    init = torch.ones_like(left[:, :1]) if change.get("init") else None
    runner(left, right, init, change.get("iters", ITERS), change.get("bf16", False))
    assert runner.captures == 2 and len(runner.graphs) == 2


def test_at_most_max_graphs_are_kept_the_least_recently_used_dropped_first():
    runner, _ = graphed(capture_after=1, max_graphs=2)
    pairs = {width: images(width, (1, 3, 32, width)) for width in (32, 64, 96)}
    for width in (32, 64, 32, 96):  # 64 is then the least recently used
        runner(*pairs[width], None, ITERS, False)
    assert [key.shape[-1] for key in runner.graphs] == [32, 96]
    runner(*pairs[64], None, ITERS, False)
    assert runner.captures == 4 and [key.shape[-1] for key in runner.graphs] == [96, 64]


def test_a_failed_capture_is_warned_about_once_and_the_key_runs_eagerly_from_then_on():
    attempts = []

    def failing_capture(run, device):
        attempts.append(run)
        raise RuntimeError("operation not permitted when stream is capturing")

    forward = RecordingForward()
    runner = GraphedForward(forward, capture=failing_capture, capture_after=1)
    left, right = images(6)
    with pytest.warns(RuntimeWarning, match="capture failed"):
        first = runner(left, right, None, ITERS, False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = runner(left, right, None, ITERS, False)
    assert len(attempts) == 1 and runner.eager_runs == 2 and runner.captures == 0
    torch.testing.assert_close(first[0], second[0])


def test_clear_drops_the_graphs_and_the_keys_seen():
    runner, _ = graphed(capture_after=2)
    left, right = images(7)
    for _ in range(2):
        runner(left, right, None, ITERS, False)
    runner.clear()
    runner(left, right, None, ITERS, False)
    assert not runner.graphs and runner.eager_runs == 2


def test_bad_bounds_are_refused():
    with pytest.raises(ValueError, match="positive"):
        GraphedForward(RecordingForward(), max_graphs=0)


def lite_on(device: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # random weights: the plumbing is what counts
        return load_model("lite", weights=None, device=device)


def random_pairs(sizes, seed=0):
    rng = np.random.default_rng(seed)
    return [
        (rng.integers(0, 256, (*s, 3), dtype=np.uint8), rng.integers(0, 256, (*s, 3), dtype=np.uint8)) for s in sizes
    ]


def test_predict_batch_runs_the_forward_through_the_graphs_and_matches_predict():
    predictor = lite_on("cpu")
    assert predictor.graphs is None  # no CUDA graphs off CUDA
    predictor.graphs = GraphedForward(predictor.forward, capture=replay_eagerly, capture_after=1)
    pairs = random_pairs([(40, 60), (33, 64)])
    lefts, rights = [p[0] for p in pairs], [p[1] for p in pairs]
    for _ in range(2):
        batch = predictor.predict_batch(lefts, rights, iters=ITERS)
    assert predictor.graphs.captures == 1 and predictor.graphs.replays == 2
    for (left, right), result in zip(pairs, batch, strict=True):
        alone = predictor.predict(left, right, iters=ITERS)
        # batched convolutions round differently: up to ~1e-5 relative on the maps
        np.testing.assert_allclose(result.disparity, alone.disparity, atol=1e-3)
        np.testing.assert_allclose(result.uncertainty, alone.uncertainty, atol=1e-4)
    assert predictor.graphs.replays == 2  # predict itself stays eager


def test_cuda_graphs_can_be_switched_off():
    assert load_model("lite", device="cpu", cuda_graphs=False).graphs is None


@needs_cuda
def test_a_captured_graph_replays_on_new_inputs_on_cuda():
    left = torch.zeros(4, device="cuda")

    def run():
        return left * 2.0, left + 1.0

    replay, (doubled, shifted) = capture_cuda_graph(run, torch.device("cuda"))
    left.copy_(torch.arange(4.0, device="cuda"))
    replay()
    torch.testing.assert_close(doubled, torch.arange(4.0, device="cuda") * 2.0)
    torch.testing.assert_close(shifted, torch.arange(4.0, device="cuda") + 1.0)


@needs_cuda
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_graph_replays_equal_the_eager_network_on_cuda(precision):
    predictor = lite_on("cuda")
    predictor.precision = precision
    pairs = random_pairs([(96, 160), (90, 150)], seed=1)
    lefts, rights = [p[0] for p in pairs], [p[1] for p in pairs]
    eager = [predictor.predict(left, right) for left, right in pairs]
    for _ in range(3):  # eager, capture + replay, replay
        graphed_results = predictor.predict_batch(lefts, rights)
    assert predictor.graphs is not None and predictor.graphs.captures == 1 and predictor.graphs.replays == 2
    tolerance = 1e-3 if precision == "fp32" else 0.05
    for alone, result in zip(eager, graphed_results, strict=True):
        np.testing.assert_allclose(result.disparity, alone.disparity, atol=tolerance)
        np.testing.assert_allclose(result.uncertainty, alone.uncertainty, atol=tolerance)


@needs_cuda
def test_the_graph_of_a_new_shape_is_its_own_on_cuda():
    predictor = lite_on("cuda")
    for size in [(64, 96)] * 2 + [(128, 96)] * 2:
        ((left, right),) = random_pairs([size])
        (result,) = predictor.predict_batch([left], [right], iters=ITERS)
        assert result.disparity.shape == size and np.isfinite(result.disparity).all()
    assert predictor.graphs is not None and predictor.graphs.captures == 2
    assert {key.shape for key in predictor.graphs.graphs} == {(1, 3, 64, 96), (1, 3, 128, 96)}
    assert all(key.iters == ITERS for key in predictor.graphs.graphs)  # the knob reached the key
