"""Spec of inference.options: one parser of iteration counts, one type for a prediction's options."""

import pytest

from crestereo_pp.inference import InferenceOptions, parse_iterations, parse_two_pass


@pytest.mark.parametrize(
    ("given", "parsed"),
    [(None, None), ("4", 4), ("1,2,4", (1, 2, 4)), (4, 4), ([1, 2, 4], (1, 2, 4)), ((2, 4, 6), (2, 4, 6)), ([7], 7)],
)
def test_iterations_read_the_same_from_a_query_a_command_line_or_python(given, parsed):
    assert parse_iterations(given) == parsed


@pytest.mark.parametrize("given", ["", "1,2", "1,2,3,4", "a", "0", "1,0,1", "100", [1, 2], [], (3, 4, 5, 6), [1.5]])
def test_iterations_other_than_one_or_three_counts_of_1_to_99_are_refused(given):
    with pytest.raises(ValueError):
        parse_iterations(given)


def test_options_are_hashable_values_that_normalise_their_iterations_and_check_the_scale():
    assert InferenceOptions(iters=[1, 2, 4]) == InferenceOptions(iters="1,2,4") == InferenceOptions(iters=(1, 2, 4))
    assert (
        len(
            {
                InferenceOptions(),
                InferenceOptions(),
                InferenceOptions(two_pass=True),
                InferenceOptions(flip=True),
                InferenceOptions(blend_sgbm=False),
                InferenceOptions(refine_edges=False),
                InferenceOptions(align_rows=False),
            }
        )
        == 6
    )
    assert InferenceOptions(scale=0.5).keywords() == {
        "iters": None,
        "two_pass": "auto",
        "scale": 0.5,
        "raw_uncertainty": False,
        "flip": False,
        "blend_sgbm": True,
        "refine_edges": True,
        "align_rows": True,
    }
    for scale in (0.0, 1.5, -1.0):
        with pytest.raises(ValueError, match="scale"):
            InferenceOptions(scale=scale)


@pytest.mark.parametrize(
    ("given", "parsed"),
    [("auto", "auto"), ("on", True), ("true", True), ("ON", True), ("off", False), ("false", False), (True, True)],
)
def test_two_pass_reads_auto_on_or_off_and_defaults_to_auto(given, parsed):
    assert parse_two_pass(given) == parsed
    assert InferenceOptions(two_pass=given).two_pass == parsed
    assert InferenceOptions().two_pass == "auto"


@pytest.mark.parametrize("given", ["", "yes please", "2", "Auto-ish"])
def test_two_pass_other_than_auto_on_or_off_is_refused(given):
    with pytest.raises(ValueError, match=r"auto, on \(true\) or off \(false\)"):
        InferenceOptions(two_pass=given)
