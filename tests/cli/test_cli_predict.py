"""`crestereo-pp predict`: output formats by extension, uncertainty and colour files, batches."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from raw_camera import (
    D1,
    D2,
    DEV_BASELINE_M,
    DEV_FOCAL_PX,
    HEIGHT,
    K1,
    K2,
    PLANE_Z,
    WIDTH,
    R,
    T,
    opencv_file,
    raw_view,
    share_within,
    small_dev_sample,
    unrectify,
)

from crestereo_pp.cli.main import main
from crestereo_pp.cli.prediction import find_pairs
from crestereo_pp.stereo_data.formats import read_kitti_disparity, read_pfm
from crestereo_pp.stereo_data.visualize import BAR_HEIGHT
from panned_frames import panned_frames

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.filterwarnings("ignore:no weights at:RuntimeWarning")


def test_one_pair_to_pfm_with_uncertainty_and_color(pairs_dir, tmp_path):
    pair = pairs_dir / "shift4"
    out, uncertainty, color = tmp_path / "d.pfm", tmp_path / "u.npy", tmp_path / "c.png"

    status = main(
        [
            "predict",
            str(pair / "left.png"),
            str(pair / "right.png"),
            "-o",
            str(out),
            "--uncertainty",
            str(uncertainty),
            "--color",
            str(color),
            "--device",
            "cpu",
        ]
    )

    assert status == 0
    disparity = read_pfm(out)
    assert disparity.shape == (64, 96) and disparity.dtype == np.float32
    assert np.isfinite(disparity).all() and (disparity >= 0).all()
    u = np.load(uncertainty)
    assert u.shape == (64, 96) and 0.0 <= u.min() and u.max() <= 1.0
    assert cv2.imread(str(color)).shape == (64 + BAR_HEIGHT, 96, 3)  # the map, then its colour bar


@pytest.mark.parametrize("suffix", [".png", ".npy"])
def test_the_output_extension_picks_the_format_and_all_formats_agree(pairs_dir, tmp_path, suffix):
    pair = pairs_dir / "shift9"
    args = ["predict", str(pair / "left.png"), str(pair / "right.png"), "--device", "cpu"]
    main([*args, "-o", str(tmp_path / "d.pfm")])
    main([*args, "-o", str(tmp_path / f"d{suffix}")])
    reference = read_pfm(tmp_path / "d.pfm")
    if suffix == ".png":  # KITTI: value * 256 in 16 bits, 0 = invalid
        decoded = read_kitti_disparity(tmp_path / "d.png")
        known = np.isfinite(decoded)
        np.testing.assert_allclose(decoded[known], reference[known], atol=0.5 / 256)
        assert (reference[~known] < 0.5 / 256).all()  # only (near-)zero disparities read back as unknown
    else:
        np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), reference)


def test_a_png_uncertainty_is_16_bit_by_the_one_rule_of_the_formats(pairs_dir, tmp_path):
    pair = pairs_dir / "shift4"
    args = [
        "predict",
        str(pair / "left.png"),
        str(pair / "right.png"),
        "-o",
        str(tmp_path / "d.pfm"),
        "--device",
        "cpu",
    ]
    main([*args, "--uncertainty", str(tmp_path / "u.npy")])
    main([*args, "--uncertainty", str(tmp_path / "u.png")])
    uncertainty = np.load(tmp_path / "u.npy").astype(np.float64)
    encoded = cv2.imread(str(tmp_path / "u.png"), cv2.IMREAD_UNCHANGED)
    assert encoded.dtype == np.uint16
    # stereo_data.formats.encode_png16: round(u x 65535), half to even; a positive u stays >= 1
    expected = np.where(uncertainty > 0, np.clip(np.rint(uncertainty * 65535), 1, 65535), 0)
    np.testing.assert_array_equal(encoded, expected)


def test_two_folders_pair_images_by_name_and_write_a_folder(tmp_path, pairs_dir):
    lefts, rights = tmp_path / "left", tmp_path / "right"
    lefts.mkdir(), rights.mkdir()
    for name in ("shift4", "shift9"):
        (lefts / f"{name}.png").symlink_to(pairs_dir / name / "left.png")
        (rights / f"{name}.png").symlink_to(pairs_dir / name / "right.png")
    out = tmp_path / "out"

    assert (
        main(
            [
                "predict",
                str(lefts),
                str(rights),
                "-o",
                str(out),
                "--format",
                "npy",
                "--color",
                str(tmp_path / "c"),
                "--mkdir",
            ]
        )
        == 0
    )

    assert sorted(p.name for p in out.iterdir()) == ["shift4.npy", "shift9.npy"]
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["shift4.png", "shift9.png"]


@pytest.mark.slow
def test_globs_pair_in_sorted_order_and_mirror_the_folders_of_the_left_images(pairs_dir, tmp_path):
    out = tmp_path / "out"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "crestereo_pp.cli.main",
            "predict",
            f"{pairs_dir}/*/left.png",
            f"{pairs_dir}/*/right.png",
            "-o",
            str(out),
            "--uncertainty",
            str(tmp_path / "u"),
            "--mkdir",
            "--device",
            "cpu",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert read_pfm(out / "shift4" / "left.pfm").shape == (64, 96)
    assert read_pfm(out / "shift9" / "left.pfm").shape == (64, 96)
    assert (tmp_path / "u" / "shift9" / "left.pfm").is_file()


def test_unmatched_inputs_are_errors(tmp_path, pairs_dir):
    lefts, rights = tmp_path / "left", tmp_path / "right"
    lefts.mkdir(), rights.mkdir()
    (lefts / "a.png").symlink_to(pairs_dir / "shift4" / "left.png")
    (rights / "b.png").symlink_to(pairs_dir / "shift4" / "right.png")
    with pytest.raises(ValueError, match="no partner"):
        find_pairs(str(lefts), str(rights))
    with pytest.raises(ValueError, match="1 left images match .* but 2 right images"):
        find_pairs(f"{pairs_dir}/shift4/left.png*", f"{pairs_dir}/*/right.png")
    with pytest.raises(ValueError, match="no left image"):
        find_pairs(str(tmp_path / "nothing*.png"), str(tmp_path / "nothing*.png"))


def test_an_input_that_names_nothing_or_a_mix_of_a_file_and_a_folder_is_refused_naming_it(pairs_dir, tmp_path, capsys):
    pair, written = pairs_dir / "shift4", tmp_path / "out"
    written.mkdir()
    out = ["-o", str(written / "d.pfm")]
    assert main(["predict", str(pair / "lefft.png"), str(pair / "right.png"), *out]) == 2
    assert f"{pair / 'lefft.png'}: no such file or folder" in capsys.readouterr().err
    assert main(["predict", str(pair), str(pair / "right.png"), *out]) == 2
    err = capsys.readouterr().err
    assert f"LEFT {pair} is a folder but RIGHT {pair / 'right.png'} is a file" in err
    assert main(["predict", str(pair / "left.png"), f"{pairs_dir}/*/right.png", *out]) == 2
    assert f"LEFT {pair / 'left.png'} is a file but RIGHT {pairs_dir}/*/right.png is a glob" in capsys.readouterr().err
    assert not list(written.iterdir())  # refused before anything was written


def test_an_unknown_output_extension_is_refused(pairs_dir, tmp_path, capsys):
    pair = pairs_dir / "shift4"
    assert main(["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.tif")]) == 2
    assert "--output" in (err := capsys.readouterr().err) and "must end in .pfm, .png, .npy" in err


@pytest.mark.parametrize(
    ("focal", "baseline", "says"),
    [("-700", "0.12", "must be positive"), ("1e-45", "1e-45", "every depth would be 0"), ("1e300", "1e300", "float32")],
)
def test_a_focal_length_and_baseline_that_give_no_usable_depth_are_refused(
    pairs_dir, tmp_path, capsys, focal, baseline, says
):
    pair = pairs_dir / "shift4"
    argv = ["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm")]
    argv += ["--depth", str(tmp_path / "z.pfm")]
    assert main([*argv, "--focal-px", focal, "--baseline-m", baseline]) == 2
    assert says in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "says"),
    [(["--scale", "0"], "scale must be in (0, 1]"), (["--iters", "0"], "each iteration count must be 1..99")],
)
def test_an_inference_option_out_of_range_is_a_usage_error_like_any_other(pairs_dir, tmp_path, capsys, option, says):
    pair = pairs_dir / "shift4"
    argv = ["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm"), *option]
    assert main(argv) == 2
    assert f"crestereo-pp predict: error: {says}" in capsys.readouterr().err


@pytest.mark.parametrize("folders", [False, True])
def test_a_colour_scale_upside_down_is_refused_before_anything_is_computed(pairs_dir, tmp_path, capsys, folders):
    pair = pairs_dir / "shift4"
    if folders:  # a run of many pairs: the first pair's files were written before the refusal
        argv = ["predict", f"{pairs_dir}/*/left.png", f"{pairs_dir}/*/right.png", "-o", str(tmp_path / "d")]
        argv += ["--color", str(tmp_path / "c"), "--mkdir"]
    else:
        argv = ["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm")]
        argv += ["--color", str(tmp_path / "c.png")]
    assert main([*argv, "--color-min", "50", "--color-max", "10"]) == 2
    assert "--color-max (10) must be above --color-min (50)" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in ("d", "d.pfm", "c", "c.png"))


def test_predict_on_a_real_pair_keeps_its_size(small_stereo_dev, tmp_path):
    pair = next(small_stereo_dev.iterdir())
    out = tmp_path / "d.pfm"
    assert (
        main(
            [
                "predict",
                str(pair / "left.png"),
                str(pair / "right.png"),
                "-o",
                str(out),
                "--two-pass",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    left = cv2.imread(str(pair / "left.png"))
    assert read_pfm(out).shape == left.shape[:2]


def test_it_says_how_far_the_right_rows_lay_off_and_when_the_rigs_calibration_needs_a_look(tmp_path, capsys):
    sample = small_dev_sample()  # Tsukuba, as given and with its right image moved 1.5 px down
    height, width = sample.left.shape[:2]
    down = cv2.warpAffine(sample.right, np.float32([[1, 0, 0], [0, 1, 1.5]]), (width, height))
    for folder, image in (("left", sample.left), ("on_rows", sample.right), ("down", down)):
        (tmp_path / folder).mkdir()
        for name in ("a", "b"):
            cv2.imwrite(str(tmp_path / folder / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    (tmp_path / "mixed").mkdir()
    (tmp_path / "mixed" / "a.png").symlink_to(tmp_path / "on_rows" / "a.png")
    (tmp_path / "mixed" / "b.png").symlink_to(tmp_path / "down" / "b.png")
    fast = ["--two-pass", "off", "--iters", "1", "1", "1", "--device", "cpu"]
    left = str(tmp_path / "left" / "a.png")

    def said(*argv: str) -> str:
        assert main(["predict", *argv, *fast]) == 0
        return capsys.readouterr().out

    assert "rows: the right image's lie on the left's (within 0." in said(
        left, str(tmp_path / "on_rows" / "a.png"), "-o", str(tmp_path / "on.pfm")
    )
    moved = said(left, str(tmp_path / "down" / "a.png"), "-o", str(tmp_path / "down.pfm"))
    assert "rows: the right image's lay up to 1.5" in moved and "check the rig's calibration" in moved
    assert "+1.5" in moved  # at the centre
    both = said(str(tmp_path / "left"), str(tmp_path / "mixed"), "-o", str(tmp_path / "out"), "--mkdir")
    assert "1 px or more off the left's in 1 of 2 pairs (up to 1.5" in both
    assert "rows:" not in said(left, str(tmp_path / "down" / "a.png"), "-o", str(tmp_path / "n.pfm"), "--no-align-rows")


def test_a_metric_point_cloud_is_written_as_ply(pairs_dir, tmp_path):
    import io

    from plyfile import PlyData

    pair = pairs_dir / "shift4"
    ply = tmp_path / "cloud.ply"
    argv = [
        "predict",
        str(pair / "left.png"),
        str(pair / "right.png"),
        "-o",
        str(tmp_path / "d.pfm"),
        "--ply",
        str(ply),
        "--focal-px",
        "500",
        "--baseline-m",
        "0.1",
        "--device",
        "cpu",
    ]
    assert main(argv) == 0
    vertex = PlyData.read(io.BytesIO(ply.read_bytes()))["vertex"]
    disparity = read_pfm(tmp_path / "d.pfm")
    kept = disparity > 1.0  # the default --min-disparity
    assert len(vertex) == int(kept.sum())
    np.testing.assert_allclose(np.sort(vertex["z"]), np.sort(50.0 / disparity[kept]), rtol=1e-4)
    assert b"comment units metres" in ply.read_bytes()[:300]
    without_baseline = [a for a in argv if a not in ("--baseline-m", "0.1")]
    assert main(without_baseline) == 2  # metric points need both --focal-px and --baseline-m


def test_every_output_is_checked_before_computing_and_every_written_file_is_named(pairs_dir, tmp_path, capsys):
    pair = pairs_dir / "shift4"
    inputs = ["predict", str(pair / "left.png"), str(pair / "right.png"), "--device", "cpu"]
    missing = tmp_path / "new" / "d.pfm"
    assert main([*inputs, "-o", str(missing), "--color", str(tmp_path / "c.jpg")]) == 2
    assert "does not exist" in capsys.readouterr().err and not missing.parent.exists()
    assert main([*inputs, "-o", str(tmp_path / "d.pfm"), "--color", str(tmp_path / "c.jpg")]) == 2
    assert "--color" in capsys.readouterr().err and not (tmp_path / "d.pfm").exists()  # refused before computing

    argv = [*inputs, "-o", str(missing), "--uncertainty", str(tmp_path / "new" / "u.png"), "--mkdir"]
    argv += ["--depth", str(tmp_path / "new" / "z.pfm"), "--focal-px", "500", "--baseline-m", "0.1"]
    assert main([*argv, "--max-depth-m", "8"]) == 0
    rows, *printed = capsys.readouterr().out.splitlines()
    assert rows.startswith("rows: the right image's lie on the left's")  # said before computing
    assert printed == [
        f"wrote disparity {missing}",
        f"wrote uncertainty {tmp_path / 'new' / 'u.png'}",
        f"wrote depth {tmp_path / 'new' / 'z.pfm'}",
    ]
    disparity, depth = read_pfm(missing), read_pfm(tmp_path / "new" / "z.pfm")
    metric = (disparity > 1.0) & (50.0 / disparity <= 8.0)
    np.testing.assert_allclose(depth[metric], 50.0 / disparity[metric], rtol=1e-5)
    assert np.isinf(depth[~metric]).all()


def image_folders(tmp_path: Path, pairs_dir: Path, names: tuple[str, ...]) -> tuple[Path, Path]:
    """Two folders of left and right images holding the pair shift4 under each of `names`."""
    folders = tmp_path / "left", tmp_path / "right"
    for folder, side in zip(folders, ("left.png", "right.png"), strict=True):
        folder.mkdir()
        for name in names:
            (folder / name).write_bytes((pairs_dir / "shift4" / side).read_bytes())
    return folders


def test_an_output_that_would_write_over_an_input_image_is_refused_before_computing(pairs_dir, tmp_path, capsys):
    pair = pairs_dir / "shift4"
    left_bytes = (pair / "left.png").read_bytes()
    one = ["predict", str(pair / "left.png"), str(pair / "right.png"), "--device", "cpu"]
    assert main([*one, "-o", str(pair / "left.png")]) == 2
    assert f"would write over the input image {pair / 'left.png'}" in capsys.readouterr().err
    assert main([*one, "-o", str(tmp_path / "d.pfm"), "--color", str(pair / "right.png")]) == 2
    assert "--color" in capsys.readouterr().err
    left, right = image_folders(tmp_path, pairs_dir, ("a.png",))
    assert main(["predict", str(left), str(right), "-o", str(left), "--format", "png", "--device", "cpu"]) == 2
    assert f"would write over the input image {left / 'a.png'}" in capsys.readouterr().err
    assert (pair / "left.png").read_bytes() == left_bytes == (left / "a.png").read_bytes()
    assert not (tmp_path / "d.pfm").exists()


def test_two_outputs_on_one_path_or_a_folder_as_a_file_are_refused_before_computing(pairs_dir, tmp_path, capsys):
    pair = pairs_dir / "shift4"
    one = ["predict", str(pair / "left.png"), str(pair / "right.png"), "--device", "cpu"]
    assert main([*one, "-o", str(tmp_path / "same.pfm"), "--uncertainty", str(tmp_path / "same.pfm")]) == 2
    assert "--uncertainty" in (said := capsys.readouterr().err) and "--output names it too" in said
    (tmp_path / "taken.pfm").mkdir()
    assert main([*one, "-o", str(tmp_path / "taken.pfm")]) == 2
    assert "is a folder; with one pair it names a file" in capsys.readouterr().err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["pairs", "taken.pfm"]  # nothing left behind


def test_two_images_of_one_name_but_their_suffix_are_refused_as_they_would_share_their_outputs(
    pairs_dir, tmp_path, capsys
):
    left, right = image_folders(tmp_path, pairs_dir, ("x.png", "x.bmp"))
    assert main(["predict", str(left), str(right), "-o", str(tmp_path / "out"), "--mkdir", "--device", "cpu"]) == 2
    assert "would write their outputs to one name (x)" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_empty_input_folders_and_a_device_that_is_none_are_one_line_errors(pairs_dir, tmp_path, capsys):
    (tmp_path / "el").mkdir(), (tmp_path / "er").mkdir()
    assert main(["predict", str(tmp_path / "el"), str(tmp_path / "er"), "-o", str(tmp_path / "o"), "--mkdir"]) == 2
    assert f"{tmp_path / 'el'}: no images in the folder" in capsys.readouterr().err
    pair = pairs_dir / "shift4"
    argv = ["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm")]
    assert main([*argv, "--device", "banana"]) == 2
    assert capsys.readouterr().err.strip() == (
        "crestereo-pp predict: error: device 'banana' is not a torch device: use 'auto', 'cpu', 'cuda' or 'cuda:N'"
    )


@pytest.mark.parametrize(
    ("option", "needs"),
    [
        (["--color-min", "5"], "--color"),
        (["--color-max", "50"], "--color"),
        (["--cx", "40"], "--ply"),
        (["--max-uncertainty", "0.3"], "--ply"),
        (["--max-depth-m", "8", "--focal-px", "500", "--baseline-m", "0.1"], "--depth, --depth-mm or --ply"),
    ],
)
def test_an_option_given_without_the_output_it_shapes_is_refused_as_a_mistake(
    pairs_dir, tmp_path, capsys, option, needs
):
    pair = pairs_dir / "shift4"
    argv = ["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm")]
    assert main([*argv, *option]) == 2
    assert f"{option[0]} applies only with {needs}" in capsys.readouterr().err
    assert not (tmp_path / "d.pfm").exists()


def test_a_colour_scale_end_that_is_not_a_number_is_refused(pairs_dir, tmp_path, capsys):
    pair = pairs_dir / "shift4"
    argv = ["predict", str(pair / "left.png"), str(pair / "right.png"), "-o", str(tmp_path / "d.pfm")]
    assert main([*argv, "--color", str(tmp_path / "c.png"), "--color-min", "nan"]) == 2
    assert "--color-min must be a finite number, got nan" in capsys.readouterr().err


def test_ctrl_c_in_a_run_of_many_pairs_says_how_many_were_written_and_leaves_only_whole_files(pairs_dir, tmp_path):
    names = tuple(f"{index:02d}.png" for index in range(40))
    left, right = image_folders(tmp_path, pairs_dir, names)
    out = tmp_path / "out"
    command = [sys.executable, "-m", "crestereo_pp.cli.main", "predict", str(left), str(right), "-o", str(out)]
    run = subprocess.Popen(
        [*command, "--uncertainty", str(tmp_path / "u"), "--mkdir", "--backend", "torch", "--device", "cpu"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # Ctrl-C acts as at a terminal whatever this process inherited (an ignored SIGINT is inherited)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 120
        while not (out.is_dir() and any(out.glob("*.pfm"))) and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        run.send_signal(signal.SIGINT)
        _, said = run.communicate(timeout=60)
    finally:
        run.kill()
    disparities, uncertainties = (sorted(folder.iterdir()) for folder in (out, tmp_path / "u"))
    lines = said.strip().splitlines()
    assert run.returncode == 130 and "Traceback" not in said, said
    assert lines[-2:] == [  # a pair is written once its last output (the uncertainty) is
        f"{len(uncertainties)} of 40 pair(s) written before the interrupt, each whole",
        "crestereo-pp predict: interrupted",
    ]
    assert 1 <= len(uncertainties) <= len(disparities) <= len(uncertainties) + 1 < 41
    for path in disparities + uncertainties:  # no partial file, each one whole
        assert not path.name.startswith(".") and read_pfm(path).shape == (64, 96)


def test_a_pair_of_two_sizes_is_named_in_image_terms(pairs_dir, tmp_path, capsys):
    right = cv2.imread(str(pairs_dir / "shift4" / "right.png"))
    cv2.imwrite(str(tmp_path / "narrow.png"), right[:, :80])
    argv = [
        "predict",
        str(pairs_dir / "shift4" / "left.png"),
        str(tmp_path / "narrow.png"),
        "-o",
        str(tmp_path / "d.pfm"),
    ]
    assert main([*argv, "--device", "cpu"]) == 2
    assert "is 96x64 but" in (err := capsys.readouterr().err) and "narrow.png is 80x64" in err


def test_a_raw_pair_with_its_calibration_gives_metric_depth_in_the_rectified_or_the_original_frame(tmp_path, capsys):
    left, right = raw_view(K1, D1, np.eye(3), np.zeros(3)), raw_view(K2, D2, R, T)
    for name, image in (("left.png", left), ("right.png", right)):
        cv2.imwrite(str(tmp_path / name), np.clip(image, 0, 255).astype(np.uint8))
    calibration = opencv_file(tmp_path / "stereo.yaml")
    inputs = [str(tmp_path / "left.png"), str(tmp_path / "right.png"), "--calibration", str(calibration)]
    assert main(["predict", *inputs, "-o", str(tmp_path / "d.pfm"), "--depth", str(tmp_path / "z.pfm")]) == 0
    depth = read_pfm(tmp_path / "z.pfm")
    assert depth.shape == (HEIGHT, WIDTH)
    middle = depth[60:-60, 100:-60]  # the plane, away from the borders the rectification leaves black
    assert np.median(middle) == pytest.approx(PLANE_Z, rel=0.08)  # metres, from the calibration alone

    original = ["-o", str(tmp_path / "d0.pfm"), "--depth", str(tmp_path / "z0.pfm"), "--frame", "original"]
    assert main(["predict", *inputs, *original]) == 0
    depth_original = read_pfm(tmp_path / "z0.pfm")
    assert depth_original.shape == (HEIGHT, WIDTH)
    assert np.median(depth_original[60:-60, 100:-60]) == pytest.approx(PLANE_Z, rel=0.08)
    assert np.isinf(depth_original).any()  # the corners the rectified image does not cover
    assert "wrote depth" in capsys.readouterr().out

    assert main(["predict", *inputs, "-o", str(tmp_path / "x.pfm"), "--focal-px", "400", "--baseline-m", "0.1"]) == 2
    assert "leave out --focal-px" in capsys.readouterr().err
    bad = opencv_file(tmp_path / "bad.yaml", T=np.zeros(3))
    assert main(["predict", *inputs[:2], "--calibration", str(bad), "-o", str(tmp_path / "y.pfm")]) == 2
    assert "T: the baseline is zero" in capsys.readouterr().err


@pytest.mark.parametrize("change", ["rotation", "distortion"])
def test_a_real_pair_made_raw_gives_its_true_depth_about_as_well_as_the_rectified_pair(tmp_path, change):
    """As over HTTP: the smallest dev pair made raw by a known camera change, with its calibration,
    gives depth on the raw left pixels within 5 % of the truth about as often as the rectified pair
    does with --focal-px and --baseline-m (the network's answers, as over HTTP)."""
    sample = small_dev_sample()
    raw = unrectify(sample.left, sample.right, sample.disparity, change)
    for name, image in (
        ("left", sample.left),
        ("right", sample.right),
        ("raw_left", raw.left),
        ("raw_right", raw.right),
    ):
        cv2.imwrite(str(tmp_path / f"{name}.png"), image[:, :, ::-1])
    calibration = opencv_file(tmp_path / "camera.yaml", **raw.calibration)
    camera = [
        "--focal-px",
        str(DEV_FOCAL_PX),
        "--baseline-m",
        str(DEV_BASELINE_M),
        "--no-blend-sgbm",
        "--no-refine-edges",
    ]
    rectified = [str(tmp_path / "left.png"), str(tmp_path / "right.png"), "-o", str(tmp_path / "d.pfm"), *camera]
    assert main(["predict", *rectified, "--depth", str(tmp_path / "z.pfm")]) == 0
    raw_inputs = [str(tmp_path / "raw_left.png"), str(tmp_path / "raw_right.png"), "--calibration", str(calibration)]
    outputs = ["-o", str(tmp_path / "d0.pfm"), "--depth", str(tmp_path / "z0.pfm"), "--frame", "original"]
    outputs += ["--no-blend-sgbm", "--no-refine-edges"]
    assert main(["predict", *raw_inputs, *outputs]) == 0
    with np.errstate(divide="ignore"):
        truth = np.where(sample.valid, DEV_FOCAL_PX * DEV_BASELINE_M / sample.disparity, np.nan)
    baseline = share_within(read_pfm(tmp_path / "z.pfm"), truth)
    share = share_within(read_pfm(tmp_path / "z0.pfm"), raw.depth)
    assert baseline > 0.4 and share >= baseline - 0.05


def test_a_sequence_of_frames_warm_starts_each_frame_and_a_stereo_video_is_read_frame_by_frame(tmp_path, capsys):
    frames = panned_frames(3, seed=5)
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
    for index, (left, right) in enumerate(frames):
        cv2.imwrite(str(tmp_path / "left" / f"{index:03d}.png"), left[:, :, ::-1])
        cv2.imwrite(str(tmp_path / "right" / f"{index:03d}.png"), right[:, :, ::-1])
    folders = [str(tmp_path / "left"), str(tmp_path / "right"), "--iters", "1", "1", "2"]
    assert main(["predict", *folders, "-o", str(tmp_path / "cold"), "--mkdir"]) == 0
    assert main(["predict", *folders, "-o", str(tmp_path / "warm"), "--mkdir", "--sequence", "--warm-iters", "3"]) == 0
    assert "wrote 3 disparity files" in capsys.readouterr().out
    cold, warm = ([read_pfm(tmp_path / run / f"{i:03d}.pfm") for i in range(3)] for run in ("cold", "warm"))
    np.testing.assert_array_equal(cold[0], warm[0])  # the first frame starts cold
    assert all(not np.array_equal(c, w) for c, w in zip(cold[1:], warm[1:], strict=True))  # the others warm

    for side in (0, 1):  # the same frames as two videos of one stereo camera
        video = cv2.VideoWriter(str(tmp_path / f"{side}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (128, 64))
        for frame in frames:
            video.write(np.ascontiguousarray(frame[side][:, :, ::-1]))
        video.release()
    videos = [str(tmp_path / "0.avi"), str(tmp_path / "1.avi"), "--sequence"]
    assert (
        main(["predict", *videos, "-o", str(tmp_path / "video"), "--mkdir", "--uncertainty", str(tmp_path / "u")]) == 0
    )
    assert sorted(p.name for p in (tmp_path / "video").iterdir()) == [f"frame_{i:06d}.pfm" for i in range(3)]
    assert read_pfm(tmp_path / "video" / "frame_000002.pfm").shape == (64, 128)
    assert main(["predict", *folders, "-o", str(tmp_path / "x"), "--mkdir", "--warm-iters", "3"]) == 2
    assert "--warm-iters needs --sequence" in capsys.readouterr().err
