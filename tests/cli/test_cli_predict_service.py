"""`crestereo-pp predict --url`: the pairs computed by a running service (a real uvicorn process),
the outputs written here as the model here writes them; a sequence over one stream."""

from pathlib import Path

import cv2
import httpx
import numpy as np

from crestereo_pp.cli.main import main
from crestereo_pp.stereo_data.formats import read_pfm
from panned_frames import panned_frames
from service_helpers import metric_total


def answered(base_url: str) -> tuple[float, float]:
    """How many requests the service has answered 200, and how many batches it has computed."""
    text = httpx.get(f"{base_url}/metrics").text
    return metric_total(text, "crestereo_requests_total", status="200"), metric_total(
        text, "crestereo_compute_seconds_count"
    )


def write_frames(folder: Path, frames: list[tuple[np.ndarray, np.ndarray]]) -> list[str]:
    """The frames as two folders of PNGs (left/, right/); their paths as predict's LEFT and RIGHT."""
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True)
    for index, (left, right) in enumerate(frames):
        cv2.imwrite(str(folder / "left" / f"{index:03d}.png"), left[:, :, ::-1])
        cv2.imwrite(str(folder / "right" / f"{index:03d}.png"), right[:, :, ::-1])
    return [str(folder / "left"), str(folder / "right")]


def test_a_pair_computed_by_a_running_service_gives_the_files_the_model_here_gives(default_server, pairs_dir, tmp_path):
    pair = pairs_dir / "shift4"
    inputs = [str(pair / "left.png"), str(pair / "right.png"), "--iters", "1", "1", "2", "--flip"]
    outputs = {name: tmp_path / name for name in ("here", "there")}
    before = answered(default_server.base_url)
    for name, where in (("here", []), ("there", ["--url", default_server.base_url])):
        folder = outputs[name]
        folder.mkdir()
        files = ["-o", str(folder / "d.pfm"), "--uncertainty", str(folder / "u.pfm"), "--ply", str(folder / "c.ply")]
        camera = ["--focal-px", "500", "--baseline-m", "0.12", "--depth", str(folder / "z.pfm")]
        assert main(["predict", *inputs, *files, *camera, *where]) == 0
    for name in ("d.pfm", "u.pfm", "z.pfm"):
        here, there = (read_pfm(outputs[where] / name) for where in ("here", "there"))
        finite = np.isfinite(here)
        assert np.array_equal(finite, np.isfinite(there))
        np.testing.assert_allclose(there[finite], here[finite], rtol=1e-4, atol=1e-3)
    assert (outputs["there"] / "c.ply").stat().st_size > 0
    assert answered(default_server.base_url) == (before[0] + 1, before[1] + 1)  # computed there, once


def test_a_sequence_goes_to_the_service_over_one_stream_warm_started_as_here(default_server, tmp_path, capsys):
    folders = write_frames(tmp_path / "frames", panned_frames(3))
    options = [*folders, "--iters", "1", "1", "2", "--sequence", "--warm-iters", "3", "--mkdir"]
    assert main(["predict", *options, "-o", str(tmp_path / "here")]) == 0
    before = answered(default_server.base_url)
    assert main(["predict", *options, "-o", str(tmp_path / "there"), "--url", default_server.base_url]) == 0
    assert "wrote 3 disparity files" in capsys.readouterr().out
    assert answered(default_server.base_url) == (before[0], before[1] + 3)  # three frames, none a POST: a stream
    for index in range(3):
        here, there = (read_pfm(tmp_path / where / f"{index:03d}.pfm") for where in ("here", "there"))
        np.testing.assert_allclose(there, here, rtol=1e-4, atol=1e-3)


def test_a_service_that_refuses_or_cannot_be_reached_and_local_model_options_are_one_line_errors(
    default_server, pairs_dir, tmp_path, capsys
):
    pair = pairs_dir / "shift4"
    inputs = [str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm")]
    assert main(["predict", *inputs, "--url", default_server.base_url, "--scale", "0.01"]) == 2
    assert "answered 422 scale_too_small" in capsys.readouterr().err
    assert main(["predict", *inputs, "--url", "http://127.0.0.1:9"]) == 2  # nothing listens there
    assert "no answer from the service at http://127.0.0.1:9" in capsys.readouterr().err
    assert main(["predict", *inputs, "--url", "127.0.0.1:8000"]) == 2  # no scheme
    assert "the service's address starts with http:// or https:// (for example http://127.0.0.1:8000)" in (
        capsys.readouterr().err
    )
    assert main(["predict", *inputs, "--url", default_server.base_url, "--weights", "w.pt", "--backend", "torch"]) == 2
    assert "--weights, --backend: with --url the service computes the pairs" in capsys.readouterr().err
    assert not (tmp_path / "d.pfm").exists()
