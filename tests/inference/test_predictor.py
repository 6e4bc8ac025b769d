"""The inference API users and the service build on: load_model(...).predict(left, right)."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from crestereo_pp.inference import NETWORK_ONLY, InferenceOptions, load_model
from crestereo_pp.inference import two_pass as two_pass_module
from crestereo_pp.inference.device import resolve_device
from crestereo_pp.inference.scaling import maps_at, resize_images
from crestereo_pp.model import ModelConfig
from crestereo_pp.model.network import finest_stage_only
from crestereo_pp.model.weights import file_sha256
from crestereo_pp.stereo_data.readers import open_dataset
from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator
from panned_frames import panned_frames
from tests.shared_data import SMALL_STEREO_DEV_PAIR, STEREO_DEV

REPO = Path(__file__).resolve().parents[2]


def random_pair(height, width, seed=0, channels=3):
    rng = np.random.default_rng(seed)
    shape = (height, width, channels) if channels else (height, width)
    return rng.integers(0, 256, shape, dtype=np.uint8), rng.integers(0, 256, shape, dtype=np.uint8)


def bt601_grey(image):
    """The grey image (HxW, float32) of an RGB one, by the luma weights 0.299, 0.587, 0.114."""
    return image.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)


def test_a_pair_of_one_grey_and_one_colour_image_is_computed_as_the_grey_pair(lite):
    left, right = random_pair(64, 96, seed=3)
    grey_left, grey_right = (np.rint(bt601_grey(image)).astype(np.uint8) for image in (left, right))
    as_grey = lite.predict(grey_left, grey_right, iters=(1, 1, 1)).disparity
    for mixed in (
        (left, grey_right),  # a colour left, a grey right
        (np.repeat(grey_left[..., None], 3, axis=2), right),  # grey stored as RGB counts as grey
    ):
        np.testing.assert_array_equal(lite.predict(*mixed, iters=(1, 1, 1)).disparity, as_grey)
    # HxWx1, and a float image: made grey in its dtype, unrounded
    np.testing.assert_array_equal(
        lite.predict(grey_left[..., None], right.astype(np.float32), iters=(1, 1, 1)).disparity,
        lite.predict(grey_left, bt601_grey(right), iters=(1, 1, 1)).disparity,
    )
    colour = lite.predict(left, right, iters=(1, 1, 1)).disparity
    assert not np.array_equal(colour, as_grey)  # two colour images stay in colour


@pytest.mark.parametrize(("height", "width"), [(40, 60), (33, 77), (375, 1242), (65, 31)])
def test_output_has_the_input_size_for_any_size(lite, height, width):
    left, right = random_pair(height, width)
    disparity, uncertainty = lite.predict(left, right, iters=(1, 1, 1))
    assert disparity.shape == uncertainty.shape == (height, width)
    assert disparity.dtype == uncertainty.dtype == np.float32
    assert (disparity >= 0).all() and ((uncertainty >= 0) & (uncertainty <= 1)).all()


def test_a_batch_of_two_pairs_equals_the_two_pairs_run_alone(lite):
    # procedural scenes, not noise: on noise a pixel's match is arbitrary, and a rounding difference
    # between the batched and the single convolutions can tip it (seen: 0.005 px on one pixel)
    scenes = SceneGenerator(SceneConfig(height=48, width=80, max_disparity=24.0)).generate(batch_size=2, seed=5)
    pairs = [scenes.pair(i) for i in range(2)]
    batch_left = torch.from_numpy(np.stack([p[0] for p in pairs])).permute(0, 3, 1, 2)
    batch_right = torch.from_numpy(np.stack([p[1] for p in pairs])).permute(0, 3, 1, 2)
    batched = lite.predict(batch_left, batch_right)
    assert batched.disparity.shape == (2, 48, 80)
    for i, (left, right) in enumerate(pairs):
        alone = lite.predict(left, right)
        # batched convolutions round differently: up to ~1e-5 relative on the maps
        np.testing.assert_allclose(batched.disparity[i].numpy(), alone.disparity, atol=1e-3)
        np.testing.assert_allclose(batched.uncertainty[i].numpy(), alone.uncertainty, atol=1e-4)


def test_the_same_input_twice_gives_the_same_output(lite):
    left, right = random_pair(50, 70, seed=3)
    first, second = lite.predict(left, right), lite.predict(left, right)
    assert np.array_equal(first.disparity, second.disparity)
    assert np.array_equal(first.uncertainty, second.uncertainty)


def test_grayscale_inputs_equal_their_rgb_replication(lite):
    left, right = random_pair(40, 64, seed=4, channels=0)
    gray = lite.predict(left, right)
    gray1 = lite.predict(left[..., None], right[..., None])
    rgb = lite.predict(np.repeat(left[..., None], 3, 2), np.repeat(right[..., None], 3, 2))
    assert np.array_equal(gray.disparity, rgb.disparity) and np.array_equal(gray1.disparity, rgb.disparity)


def test_sixteen_bit_images_are_scaled_to_the_eight_bit_range(lite):
    left, right = random_pair(32, 64, seed=5)
    wide = lite.predict(left.astype(np.uint16) * 257, right.astype(np.uint16) * 257)
    np.testing.assert_allclose(wide.disparity, lite.predict(left, right).disparity, atol=1e-3)


def near_and_far_scenes(height=192, width=224):
    """(B=2, 3, H, W) left and right images: a scene with disparities to 48 px, one to 8 px."""
    near, far = (
        SceneGenerator(SceneConfig(height=height, width=width, max_disparity=d)).generate(batch_size=1, seed=8)
        for d in (48.0, 8.0)
    )
    return torch.cat([near.left, far.left]), torch.cat([near.right, far.right])


def test_auto_two_pass_computes_each_pair_of_a_batch_as_its_quick_pass_says(lite, monkeypatch):
    """A pair whose quick quarter-resolution pass puts its 99th percentile above the threshold is
    computed in two passes, the others in one, also when the two share a batch (enlarging left
    out here: the next test)."""
    monkeypatch.setattr(two_pass_module, "ENLARGEMENTS", ())
    left, right = near_and_far_scenes()
    evidence = lite.large_disparity_percentile(left, right)
    assert evidence[0] > evidence[1] + 5  # the scene with the larger disparities says so
    monkeypatch.setattr(two_pass_module, "LARGE_DISPARITY_PX", float(evidence.mean()))
    auto = lite.predict(left, right, two_pass="auto")
    for i, two in ((0, True), (1, False)):
        alone = lite.predict(left[i : i + 1], right[i : i + 1], two_pass=two)
        other = lite.predict(left[i : i + 1], right[i : i + 1], two_pass=not two)
        np.testing.assert_allclose(auto.disparity[i].numpy(), alone.disparity[0].numpy(), atol=1e-3)
        assert not np.allclose(auto.disparity[i].numpy(), other.disparity[0].numpy(), atol=1e-3)


def test_auto_enlarges_a_pair_with_small_disparities_and_brings_its_maps_back_to_its_size(lite, monkeypatch):
    """With "auto", the pair whose quick pass finds small disparities is computed as the network
    sees it enlarged 1.5x in one pass (its disparity shrunk back, in its own pixels), beside a pair
    in two passes in the same batch."""
    left, right = near_and_far_scenes()
    evidence = lite.large_disparity_percentile(left, right)
    monkeypatch.setattr(two_pass_module, "LARGE_DISPARITY_PX", float(evidence.mean()))
    monkeypatch.setattr(two_pass_module, "ENLARGED_DISPARITY_PX", float(evidence[1]) * 1.5)
    ways = [two_pass_module.auto_way(float(value), 192, 224) for value in evidence]
    assert ways == [(True, 1.0), (False, 1.5)]  # the near scene's range is too wide to enlarge
    auto = lite.predict(left, right, two_pass="auto", **NETWORK_ONLY)  # the network's own answers
    assert auto.disparity.shape == auto.uncertainty.shape == (2, 192, 224)
    two_passes = lite.predict(left[:1], right[:1], two_pass=True, **NETWORK_ONLY)
    np.testing.assert_allclose(auto.disparity[0].numpy(), two_passes.disparity[0].numpy(), atol=1e-3)
    enlarged = lite.predict(
        resize_images(left[1:], (288, 336)),
        resize_images(right[1:], (288, 336)),
        two_pass=False,
        raw_uncertainty=True,
        **NETWORK_ONLY,
    )
    disparity, _ = maps_at((enlarged.disparity[:, None], enlarged.uncertainty[:, None]), 192, 224)
    np.testing.assert_allclose(auto.disparity[1].numpy(), disparity[0, 0].numpy(), atol=1e-3)
    own_size = lite.predict(left[1:], right[1:], two_pass=False, **NETWORK_ONLY)
    assert not np.allclose(auto.disparity[1].numpy(), own_size.disparity[0].numpy(), atol=1e-2)


def test_auto_shrinks_a_pair_whose_disparities_two_passes_cannot_hold_and_brings_its_maps_back(lite, monkeypatch):
    """Where even the half-resolution pass would see more than SHRINK_ABOVE_PX, "auto" computes
    the pair smaller in two passes, as ``scale`` would (its disparity in the pair's own pixels);
    the other pair of the batch is computed as before."""
    left, right = near_and_far_scenes()
    evidence = lite.large_disparity_percentile(left, right)
    assert evidence[0] > 3 * evidence[1]
    monkeypatch.setattr(two_pass_module, "LARGE_DISPARITY_PX", float(evidence[0]) / 3)  # the near in two passes
    monkeypatch.setattr(two_pass_module, "SHRINK_ABOVE_PX", float(evidence[0]) / 2 - 1)  # and shrunk by 2/3
    monkeypatch.setattr(two_pass_module, "MIN_SHRUNK_SIDE", 96)  # of its 192 px
    ways = [two_pass_module.auto_way(float(value), 192, 224) for value in evidence]
    assert ways[0][0] and ways[0][1] < 1 and not ways[1][0]
    auto = lite.predict(left, right, two_pass="auto")
    assert auto.disparity.shape == auto.uncertainty.shape == (2, 192, 224)
    shrunk = lite.predict(left[:1], right[:1], two_pass=True, scale=ways[0][1])
    np.testing.assert_allclose(auto.disparity[0].numpy(), shrunk.disparity[0].numpy(), atol=1e-3)
    at_its_size = lite.predict(left[:1], right[:1], two_pass=True)
    assert not np.allclose(auto.disparity[0].numpy(), at_its_size.disparity[0].numpy(), atol=1e-2)


def test_auto_never_enlarges_a_pair_shrunk_by_scale(lite):
    left, right = near_and_far_scenes(512, 576)  # the far scene at scale 0.5: 256 x 288
    shrunk = [resize_images(image[1:], (256, 288)) for image in (left, right)]
    evidence = float(lite.large_disparity_percentile(*shrunk)[0])
    assert two_pass_module.auto_way(evidence, 256, 288) == (False, 1.5)  # what it would be at its size
    auto = lite.predict(left[1:], right[1:], two_pass="auto", scale=0.5)
    one_pass = lite.predict(left[1:], right[1:], two_pass=False, scale=0.5)
    np.testing.assert_allclose(auto.disparity.numpy(), one_pass.disparity.numpy(), atol=1e-3)


def test_auto_enlarges_as_far_as_the_pass_that_finds_the_disparities_holds_their_range():
    """How "auto" computes a pair from its quick pass's 99th percentile (px) and its size."""
    way = two_pass_module.auto_way
    assert way(60.0, 375, 1242) == (False, 1.5)  # one pass: 90 px enlarged, within ENLARGED_DISPARITY_PX (100)
    assert way(75.0, 375, 1242) == (False, 1.25)  # 1.5x would reach 112 px
    assert way(85.0, 375, 1242) == (False, 1.0)  # 1.25x would reach 106 px
    assert way(95.0, 375, 1242) == (True, 1.5)  # above LARGE_DISPARITY_PX (90): two passes, whose
    assert way(130.0, 375, 1242) == (True, 1.25)  # half-resolution pass sees 71 and 81 px enlarged
    assert way(150.0, 375, 1242) == (True, 1.0)  # 1.25x: 94 px at half resolution
    assert way(20.0, 720, 1280) == (False, 1.0)  # 1.25x would be 1.44 M pixels, over MAX_ENLARGED_PIXELS
    assert way(20.0, 720, 960) == (False, 1.25)  # 1.08 M pixels; 1.5x would be 1.56 M
    assert way(20.0, 375, 1242, resize=False) == (False, 1.0)
    assert way(95.0, 375, 1242, resize=False) == (True, 1.0)


def test_auto_shrinks_a_pair_whose_half_resolution_pass_would_see_more_than_a_pass_holds():
    """Two passes whose half-resolution pass would see more than SHRINK_ABOVE_PX (140 px): the
    pair shrunk so that it sees about LARGE_DISPARITY_PX (90), by a multiple of 1/8."""
    way = two_pass_module.auto_way
    assert way(280.0, 1080, 1920) == (True, 1.0)  # 140 px: not beyond what a pass may hold
    assert way(290.0, 1080, 1920) == (True, 0.625)  # 145 px: 90 / 145 = 0.62
    assert way(380.0, 1080, 1920) == (True, 0.5)  # 190 px: 0.47
    assert way(1000.0, 1080, 1920) == (True, 0.375)  # 0.18, but a side keeps 384 px (1080 x 0.375 = 405)
    assert way(1000.0, 3000, 4000) == (True, 0.25)  # 0.18, rounded to the nearest 1/8 above 384 / 3000
    assert way(300.0, 375, 1242) == (True, 1.0)  # a side under 384 px: never shrunk
    assert way(300.0, 1080, 1920, resize=False) == (True, 1.0)  # the caller's scale is kept


def test_the_quick_pass_reads_again_at_eighth_resolution_the_pairs_whose_range_it_cannot_hold(lite, monkeypatch):
    """Where the quarter-resolution pass sees more than QUICK_PASS_HOLDS_PX, the pair's evidence
    is an eighth-resolution pass's reading; the other pair of the batch keeps its quarter one, and
    a pair too small for an eighth-resolution pass (under 384 px a side) keeps its own."""
    iters, forward = lite.config.iters, lite.padded_forward()
    for height, width, reads_again in ((384, 448, True), (192, 224, False)):
        left, right = near_and_far_scenes(height, width)
        with torch.inference_mode():
            quarter = two_pass_module.quick_pass_percentile(left, right, iters, forward, 4)
            eighth = two_pass_module.quick_pass_percentile(left[:1], right[:1], iters, forward, 8)
        assert quarter[0] > quarter[1] + 5 and abs(float(eighth[0] - quarter[0])) > 0.1
        monkeypatch.setattr(two_pass_module, "QUICK_PASS_HOLDS_PX", float(quarter.mean()) / 4)  # the near one only
        evidence = lite.large_disparity_percentile(left, right)
        assert float(evidence[0]) == pytest.approx(float((eighth if reads_again else quarter)[0]), abs=1e-3)
        assert float(evidence[1]) == pytest.approx(float(quarter[1]), abs=1e-3)


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_auto_reads_the_range_of_a_real_pair_whose_disparities_pass_what_the_quarter_pass_sees(lite):
    """SceneFlow A0032 enlarged 6x (5760 x 3240, disparities to about 770 px): auto's evidence is
    within 3 % of the 99th percentile, where the quarter-resolution pass alone read 569 px for 766."""
    import cv2

    dataset = open_dataset(STEREO_DEV)
    sample = next(dataset[i] for i in range(len(dataset)) if dataset[i].name == "sceneflow_ft3d_A0032_0006")
    truth = 6 * float(np.percentile(sample.disparity[sample.valid], 99))
    size = (6 * sample.left.shape[1], 6 * sample.left.shape[0])
    left, right = (
        torch.from_numpy(cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)).permute(2, 0, 1)[None].float()
        for image in (sample.left, sample.right)
    )
    assert float(lite.large_disparity_percentile(left, right)[0]) == pytest.approx(truth, rel=0.03)


@pytest.mark.skipif(not STEREO_DEV.is_dir(), reason=f"no real stereo pairs at {STEREO_DEV}")
def test_the_quick_pass_reads_a_real_pairs_largest_disparities_and_auto_enlarges_a_near_scene_to_its_gain(lite):
    from crestereo_pp.evaluation.metrics import compute_metrics

    dataset = open_dataset(STEREO_DEV)
    sample = next(dataset[i] for i in range(len(dataset)) if dataset[i].name == SMALL_STEREO_DEV_PAIR)
    truth = float(np.percentile(sample.disparity[sample.valid], 99))  # tsukuba: 14 px
    evidence = float(
        lite.large_disparity_percentile(
            *(torch.from_numpy(image).permute(2, 0, 1)[None].float() for image in (sample.left, sample.right))
        )[0]
    )
    assert abs(evidence - truth) < 3.0
    assert two_pass_module.auto_way(evidence, *sample.left.shape[:2]) == (False, 1.5)
    auto, one = (  # the network's own answers
        lite.predict(sample.left, sample.right, two_pass=flag, **NETWORK_ONLY).disparity for flag in ("auto", False)
    )
    known = sample.valid & np.isfinite(sample.disparity)
    auto_bad2, one_bad2 = (compute_metrics(d, sample.disparity, known).bad2 for d in (auto, one))
    assert auto_bad2 < one_bad2 - 1.0, (auto_bad2, one_bad2)  # measured: 3.6 against 5.6 %


def test_warm_start_and_two_pass_give_maps_of_the_input_size(lite):
    left, right = random_pair(70, 100, seed=6)
    warm = lite.predict(left, right, init_disparity=np.full((70, 100), 3.0, np.float32))
    two_pass = lite.predict(left, right, two_pass=True)
    assert warm.disparity.shape == two_pass.disparity.shape == (70, 100)
    assert not np.array_equal(warm.disparity, lite.predict(left, right).disparity)


def test_a_start_disparity_starts_the_first_stage_that_runs(lite):
    net = lite.network
    calls = []
    hook = net.update.register_forward_hook(lambda module, args, out: calls.append(args[0].shape[-1]))
    images, start = torch.zeros(1, 3, 64, 64), torch.ones(1, 1, 64, 64)
    try:
        with torch.inference_mode():
            net(images, images, init_disparity=start)  # a warm start: every stage, from 1/16
            net(images, images, iters=finest_stage_only(net.config.iters), init_disparity=start)  # a second pass
    finally:
        hook.remove()
    assert calls == [4] * 2 + [8] * 4 + [16] * 6 + [16] * 6  # the iterations (2, 4, 6) at 1/16, 1/8, 1/4 of 64


def test_the_second_of_two_passes_refines_the_half_resolution_map_at_quarter_resolution_only(lite, monkeypatch):
    runs = []
    forward = lite.forward

    def recording(left, right, init, iters, bf16):
        runs.append((tuple(left.shape[-2:]), init is not None, iters))
        return forward(left, right, init, iters, bf16)

    monkeypatch.setattr(lite, "forward", recording)
    lite.predict(*random_pair(64, 96), two_pass=True)
    assert runs == [((32, 64), False, (2, 4, 6)), ((64, 96), True, (0, 0, 6))]  # padded to multiples of 32


def test_mismatched_or_malformed_inputs_are_refused_with_a_clear_error(lite):
    left, _ = random_pair(40, 60)
    with pytest.raises(ValueError, match="differ in size"):
        lite.predict(left, left[:, :50])
    with pytest.raises(ValueError, match="HxWx3"):
        lite.predict(left[..., :2], left[..., :2])
    with pytest.raises(TypeError, match="numpy array or a torch tensor"):
        lite.predict(left.tolist(), left.tolist())
    for bad, problem in ((left / 255.0, r"within \[0, 1\]: multiply it by 255"), (left * 300.0, "outside that range")):
        with pytest.raises(ValueError, match=problem):
            lite.predict(bad, bad)


def test_float_images_in_0_255_give_the_answer_of_their_uint8_pair(lite):
    left, right = random_pair(40, 60)
    as_floats = lite.predict(left.astype(np.float32), right.astype(np.float64), iters=(1, 1, 1))
    as_bytes = lite.predict(left, right, iters=(1, 1, 1))
    np.testing.assert_array_equal(as_floats.disparity, as_bytes.disparity)


def test_missing_weights_warn_and_give_the_same_random_network_in_every_process(monkeypatch, tmp_path):
    monkeypatch.setattr("crestereo_pp.inference.loading.WEIGHTS_DIR", tmp_path)  # no bundled weights here
    with pytest.warns(RuntimeWarning, match="randomly initialised"):
        first = load_model("lite", weights=None)
    assert first.weights_sha256 is None
    with pytest.warns(RuntimeWarning):
        second = load_model("lite")
    for a, b in zip(first.network.state_dict().values(), second.network.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_an_unknown_model_name_or_device_is_a_value_error_saying_so_and_nothing_else():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning about weights of a model that does not exist
        with pytest.raises(ValueError, match="unknown model preset 'nope'"):
            load_model("nope")
        with pytest.raises(ValueError, match="'banana' is not a torch device"):
            resolve_device("banana", 0)


def test_weights_file_round_trip_keeps_predictions_config_and_reports_its_sha256(lite, tmp_path):
    path = tmp_path / "weights.pt"
    state = {k: v.half() for k, v in lite.network.state_dict().items()}  # fp16 on disk
    config = ModelConfig.preset("lite", iters=(1, 2, 3))
    torch.save({"model": state, "config": config.to_dict(), "meta": {"steps": 0}}, path)
    with pytest.warns(RuntimeWarning, match="are untrained"):  # no validation recorded
        loaded = load_model("lite", weights=path)
    assert loaded.weights_sha256 == file_sha256(path) and len(loaded.weights_sha256) == 64
    assert loaded.config == config and loaded.num_parameters == lite.num_parameters
    left, right = random_pair(40, 60, seed=7)
    # fp16 keeps about 3 significant digits of each weight, so predictions agree to about 0.1 %.
    np.testing.assert_allclose(
        loaded.predict(left, right).disparity,
        lite.predict(left, right, iters=(1, 2, 3)).disparity,
        rtol=2e-3,
        atol=0.05,
    )


def test_missing_or_invalid_weights_files_raise(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_model("lite", weights=tmp_path / "nope.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"something": 1}, bad)
    with pytest.raises(ValueError, match="not a weights file"):
        load_model("lite", weights=bad)
    shipped = (REPO / "model/weights/lite.pt").read_bytes()
    for name, content in (
        ("image.png", b"\x89PNG\r\n\x1a\n" + bytes(64)),
        ("notes.txt", b"hello world\n"),  # torch's unpickler trips a KeyError on these bytes
        ("empty.pt", b""),
        ("cut.pt", shipped[:4096]),
    ):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=f"{name} is not a weights file or checkpoint: torch cannot read it"):
            load_model("lite", weights=tmp_path / name)


def test_weights_of_the_other_model_are_refused_naming_the_model_they_are():
    with pytest.raises(ValueError, match=r"lite\.pt holds 'lite' weights, not 'full': load them as 'lite'"):
        load_model("full", weights=REPO / "model/weights/lite.pt", backend="torch")


def test_inference_holds_no_autograd_state(lite):
    left, right = random_pair(32, 32, seed=8)
    batch = torch.from_numpy(left).permute(2, 0, 1)[None]
    out = lite.predict(batch, batch)
    assert not out.disparity.requires_grad and out.disparity.is_inference()


def test_a_scale_runs_the_network_on_the_resized_pair_and_answers_in_input_pixels(lite):
    import torch.nn.functional as F

    left, right = random_pair(96, 160, seed=3)
    network_only = {"blend_sgbm": False, "refine_edges": False}  # the refinements run at the input's size
    scaled = lite.predict(left, right, iters=(1, 1, 2), scale=0.5, **network_only)
    assert scaled.disparity.shape == scaled.uncertainty.shape == (96, 160)

    def half(image):
        batch = torch.from_numpy(image).permute(2, 0, 1)[None].float()
        return F.interpolate(batch, size=(48, 80), mode="bilinear", antialias=True, align_corners=False)

    small = lite.predict(half(left), half(right), iters=(1, 1, 2), **network_only)
    expected = 2.0 * F.interpolate(small.disparity[:, None], size=(96, 160), mode="bilinear", align_corners=False)
    np.testing.assert_allclose(scaled.disparity, expected[0, 0].numpy(), rtol=1e-4, atol=1e-4)
    for bad in (0.0, -1.0, 1.5):
        with pytest.raises(ValueError, match="scale"):
            lite.predict(left, right, scale=bad)


def test_a_batch_of_pairs_of_different_sizes_equals_each_pair_alone_as_host_arrays(lite):
    pairs = [random_pair(64, 96, seed=1), random_pair(50, 90, seed=2), random_pair(60, 70, seed=3)]
    lefts, rights = [left for left, _ in pairs], [right for _, right in pairs]
    padded = lite.predict_batch(lefts, rights, iters=(1, 1, 2), two_pass=False)
    for (left, right), result in zip(pairs, padded, strict=True):
        alone = lite.predict(left, right, iters=(1, 1, 2), two_pass=False)
        assert isinstance(result.disparity, np.ndarray) and result.disparity.shape == left.shape[:2]
        np.testing.assert_allclose(result.disparity, alone.disparity, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(result.uncertainty, alone.uncertainty, rtol=1e-4, atol=1e-4)
    # "auto" decides each pair on its own unpadded image: one batch per size, each pair as alone
    pairs[0] = random_pair(192, 200, seed=1)  # large enough for the quick pass
    lefts, rights = [left for left, _ in pairs], [right for _, right in pairs]
    for (left, right), result in zip(pairs, lite.predict_batch(lefts, rights, iters=(1, 1, 2)), strict=True):
        np.testing.assert_allclose(result.disparity, lite.predict(left, right, iters=(1, 1, 2)).disparity, atol=1e-3)
    for knob in ({"scale": 0.5}, {"two_pass": True}):
        with pytest.raises(ValueError, match="different sizes"):
            lite.predict_batch([pairs[0][0], pairs[1][0]], [pairs[0][1], pairs[1][1]], **knob)
    with pytest.raises(ValueError, match="as many"):
        lite.predict_batch([pairs[0][0]], [])


def test_pairs_of_different_padded_shapes_in_one_call_each_get_the_answer_they_get_alone(lite):
    # padded to one larger shape, a pair would see more replicated border than alone, and the
    # network's receptive field reaches across the image: each padded shape runs as its own batch
    pairs = [random_pair(64, 96, seed=1), random_pair(100, 130, seed=2), random_pair(50, 90, seed=3)]
    lefts, rights = [left for left, _ in pairs], [right for _, right in pairs]
    for knobs in ({"two_pass": False}, {"two_pass": False, "flip": True}):
        results = lite.predict_batch(lefts, rights, iters=(1, 1, 2), **knobs)
        for (left, right), result in zip(pairs, results, strict=True):
            alone = lite.predict(left, right, iters=(1, 1, 2), **knobs)
            np.testing.assert_allclose(result.disparity, alone.disparity, rtol=1e-4, atol=1e-3)
            np.testing.assert_allclose(result.uncertainty, alone.uncertainty, rtol=1e-4, atol=1e-4)


def test_bf16_autocast_keeps_the_disparity_within_0_08_px_of_fp32_on_average():
    """The disparity, pixel grids and upsampling weights stay float32 under autocast: only the
    convolutions and correlations run in bf16 (measured on the bundled lite weights, CPU autocast)."""
    scene = SceneGenerator(SceneConfig(height=96, width=320, max_disparity=48.0)).generate(batch_size=1, seed=2)
    fp32 = load_model("lite").predict(scene.left, scene.right).disparity
    bf16 = load_model("lite", precision="bf16").predict(scene.left, scene.right).disparity
    assert bf16.dtype == torch.float32
    assert (bf16 - fp32).abs().mean() < 0.08  # 0.055 measured; 0.135 with a bf16 disparity and grids


def test_a_scale_that_leaves_the_network_too_few_pixels_is_refused_not_extrapolated():
    from crestereo_pp.inference.scaling import MIN_SCALED_SIDE, scaled_size

    assert scaled_size(375, 1242, 0.5) == (188, 621)
    assert scaled_size(20, 20, 1.0) == (20, 20)  # a small image at its own size is fine
    for scale in (0.05, 1e-300):
        with pytest.raises(ValueError, match=f"at least {MIN_SCALED_SIDE} px"):
            scaled_size(64, 256, scale)
    with pytest.raises(ValueError, match="scale must be in"):
        scaled_size(64, 256, 0.0)


def test_a_sequence_starts_cold_and_warm_starts_every_next_frame_from_the_previous_one(lite):
    frames = panned_frames(3)
    options = InferenceOptions(iters=(1, 1, 2))
    results = list(lite.predict_sequence(iter(frames), options, warm_iters=3))
    assert len(results) == 3
    first = lite.predict(*frames[0], iters=(1, 1, 2))
    np.testing.assert_array_equal(results[0].disparity, first.disparity)  # the first frame is cold
    for previous, (left, right), result in zip(results, frames[1:], results[1:], strict=False):
        warm = lite.predict(left, right, iters=3, init_disparity=previous.disparity)
        np.testing.assert_array_equal(result.disparity, warm.disparity)
        assert not np.array_equal(result.disparity, lite.predict(left, right, iters=(1, 1, 2)).disparity)


def test_a_frame_of_another_size_or_after_a_restart_starts_cold(lite):
    (left, right), (small_left, small_right) = panned_frames(1)[0], panned_frames(1, 32, 64)[0]
    stream = lite.stream()
    stream.predict(left, right)
    np.testing.assert_array_equal(
        stream.predict(small_left, small_right).disparity, lite.predict(small_left, small_right).disparity
    )
    stream.restart()
    np.testing.assert_array_equal(stream.predict(left, right).disparity, lite.predict(left, right).disparity)
