"""The inference tests' shared fixture: the shipped lite, loaded once per test module."""

import warnings

import pytest

from crestereo_pp.inference import StereoPredictor, load_model


@pytest.fixture(scope="module")
def lite() -> StereoPredictor:
    """The shipped lite on the CPU's default backend (warnings of a bf16-less CPU kept quiet)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return load_model("lite", weights=None)
