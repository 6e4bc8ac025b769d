"""The weights file format (model.weights) and the one list of model names."""

from __future__ import annotations

import pytest
import torch

from crestereo_pp.inference import load_model
from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.model.config import MODEL_NAMES, PRESETS
from crestereo_pp.model.weights import model_config_of, network_from_weights, read_weights, write_weights
from tests.untrained_weights import write_untrained


def test_every_model_name_has_exactly_one_preset():
    assert MODEL_NAMES == ("lite", "full")
    assert set(PRESETS) == set(MODEL_NAMES)


def test_a_written_file_reads_back_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "sub" / "w.pt"
    network = CREStereoPP(ModelConfig.preset("lite", iters=(1, 1, 1)))
    write_weights({"model": network.state_dict(), "config": network.config.to_dict(), "step": 3}, path)
    payload = read_weights(path)
    assert payload["step"] == 3 and [p.name for p in path.parent.iterdir()] == ["w.pt"]
    rebuilt = network_from_weights(payload, "lite")
    assert rebuilt.config == network.config
    for a, b in zip(rebuilt.state_dict().values(), network.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_a_payload_without_a_state_dict_is_refused_and_the_old_file_kept(tmp_path):
    path = tmp_path / "w.pt"
    write_weights({"model": {"x": torch.ones(2)}}, path)
    with pytest.raises(ValueError, match="'model' state_dict"):
        write_weights({"step": 1}, path)
    assert torch.equal(read_weights(path)["model"]["x"], torch.ones(2))


def test_a_file_without_a_config_uses_the_preset_of_its_name():
    assert model_config_of({"model": {}}, "full") == ModelConfig.preset("full")


def test_weights_count_as_trained_only_with_a_good_validation_on_real_pairs():
    from crestereo_pp.model.weights import is_trained

    assert not is_trained(None)
    assert not is_trained({"runs": [{"validation": None}]})  # trained on scenes, never validated
    assert not is_trained({"runs": [{"validation": {"bad2": 93.6}}]})
    assert is_trained({"runs": [{"validation": {"bad2": 14.7}}, {"validation": None}]})
    assert load_model("lite").trained and load_model("full").trained  # the bundled weights


def test_loading_untrained_weights_warns_that_their_maps_are_not_usable(tmp_path):
    with pytest.warns(RuntimeWarning, match="untrained"):
        predictor = load_model("full", weights=write_untrained(tmp_path / "full.pt"))
    assert not predictor.trained
