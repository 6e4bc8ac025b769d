"""One import name: the public API is `crestereo_pp`'s, and importing a part loads only what it needs."""

import subprocess
import sys

import crestereo_pp


def test_every_public_name_resolves_to_the_object_its_subpackage_defines():
    from crestereo_pp.client import StereoClient
    from crestereo_pp.inference import load_model

    assert crestereo_pp.load_model is load_model and crestereo_pp.StereoClient is StereoClient
    for name in crestereo_pp.__all__:
        assert getattr(crestereo_pp, name).__module__.startswith("crestereo_pp."), name


def test_an_unknown_name_is_an_attribute_error():
    try:
        crestereo_pp.no_such_thing  # noqa: B018
    except AttributeError as error:
        assert "no_such_thing" in str(error)
    else:
        raise AssertionError("crestereo_pp.no_such_thing resolved")


def test_importing_the_client_does_not_load_torch():
    code = "import sys, crestereo_pp.client; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
