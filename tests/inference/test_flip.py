"""Spec of `flip`: the pair computed as given and upside down, the two answers merged."""

import numpy as np
import pytest
import torch
from raw_camera import small_dev_sample

from crestereo_pp.inference import NETWORK_ONLY, InferenceOptions
from crestereo_pp.inference.flip import AGREEMENT_PX, merge_flipped
from crestereo_pp.inference.warm_start import WarmStart


def maps(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float32).reshape(1, 1, 1, len(values))


def test_answers_that_agree_are_averaged_and_of_two_that_disagree_the_less_uncertain_is_kept():
    near = AGREEMENT_PX - 0.5
    disparity, uncertainty = merge_flipped(
        maps(10.0, 10.0, 10.0, 10.0),
        maps(0.1, 0.1, 0.2, 0.6),
        maps(10.0 + near, 10.0 + near, 20.0, 20.0),
        maps(0.3, 0.9, 0.4, 0.2),
    )
    assert disparity.flatten().tolist() == pytest.approx([10.0 + near / 2, 10.0 + near / 2, 10.0, 20.0])
    assert uncertainty.flatten().tolist() == pytest.approx([0.2, 0.5, 0.3, 0.4])  # the mean of the two


def small_real_pair() -> tuple[np.ndarray, np.ndarray]:
    sample = small_dev_sample()
    return sample.left[:192, :256], sample.right[:192, :256]  # the top left of Tsukuba


@pytest.mark.parametrize("raw_uncertainty", [False, True])
def test_flip_merges_the_answer_with_that_of_the_pair_upside_down_turned_back(lite, raw_uncertainty):
    left, right = small_real_pair()
    given = lite.predict(left, right, raw_uncertainty=raw_uncertainty, **NETWORK_ONLY)
    upside_down = lite.predict(left[::-1].copy(), right[::-1].copy(), raw_uncertainty=raw_uncertainty, **NETWORK_ONLY)
    expected = merge_flipped(
        *(
            torch.from_numpy(x.copy())[None, None]
            for x in (*given, upside_down.disparity[::-1], upside_down.uncertainty[::-1])
        )
    )
    flipped = lite.predict(left, right, raw_uncertainty=raw_uncertainty, flip=True, **NETWORK_ONLY)
    np.testing.assert_allclose(flipped.disparity, expected[0][0, 0].numpy(), atol=1e-4)
    np.testing.assert_allclose(flipped.uncertainty, expected[1][0, 0].numpy(), atol=1e-5)
    # a real pair: the two answers differ somewhere, and the merge is neither of them
    assert not np.allclose(flipped.disparity, given.disparity, atol=1e-3)
    assert not np.allclose(flipped.disparity, upside_down.disparity[::-1], atol=1e-3)


def test_flip_turns_each_pair_of_a_padded_batch_within_its_own_size(lite):
    rng = np.random.default_rng(4)
    sizes = [(64, 96), (50, 90), (60, 70)]  # padded to 64x96 in the batch as each is alone
    pairs = [tuple(rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(2)) for h, w in sizes]
    batched = lite.predict_batch(
        [p[0] for p in pairs], [p[1] for p in pairs], iters=(1, 1, 2), two_pass=False, flip=True
    )
    for (left, right), result in zip(pairs, batched, strict=True):
        alone = lite.predict(left, right, iters=(1, 1, 2), two_pass=False, flip=True)
        assert result.disparity.shape == left.shape[:2]
        np.testing.assert_allclose(result.disparity, alone.disparity, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(result.uncertainty, alone.uncertainty, rtol=1e-4, atol=1e-4)


def test_a_streams_warm_frames_keep_its_flip():
    assert WarmStart(InferenceOptions(flip=True), warm_iters=3).warm_options.flip
    assert not WarmStart(InferenceOptions(), warm_iters=3).warm_options.flip


def test_a_warm_start_is_turned_with_its_pair(lite):
    left, right = small_real_pair()
    start = lite.predict(left, right, iters=(1, 1, 2)).disparity
    given = lite.predict(left, right, iters=(1, 1, 2), init_disparity=start, **NETWORK_ONLY)
    upside_down = lite.predict(
        left[::-1].copy(),
        right[::-1].copy(),
        iters=(1, 1, 2),
        init_disparity=start[::-1].copy(),
        **NETWORK_ONLY,
    )
    expected = merge_flipped(
        *(
            torch.from_numpy(x.copy())[None, None]
            for x in (*given, upside_down.disparity[::-1], upside_down.uncertainty[::-1])
        )
    )
    flipped = lite.predict(left, right, iters=(1, 1, 2), init_disparity=start, flip=True, **NETWORK_ONLY)
    np.testing.assert_allclose(flipped.disparity, expected[0][0, 0].numpy(), atol=1e-4)
