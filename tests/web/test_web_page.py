"""The web page at `/`, in a real headless Chromium against the real app on a real uvicorn: it loads
with nothing from another origin, runs a bundled example pair into three pictures with colour bars
in px, shows the values under the mouse (and metric depth with a calibration), downloads every
format, accepts dropped files, and shows the service's own JSON error for a bad upload."""

from __future__ import annotations

import base64
import importlib.util
import json
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from raw_camera import D1, D2, K1, K2, PLANE_Z, R, T, opencv_file, raw_view, small_dev_sample
from raw_camera import HEIGHT as RAW_HEIGHT
from raw_camera import WIDTH as RAW_WIDTH

from crestereo_pp.service.api.routes.page import STATIC_DIR
from crestereo_pp.service.api.schemas import OutputFormat
from crestereo_pp.stereo_data.rig import read_rig
from crestereo_pp.stereo_data.visualize import DISPARITY_COLORMAP, PREVIEW_GAP, colorize, robust_range
from service_helpers import Server, run_uvicorn
from tests.untrained_weights import write_untrained
from web_helpers import WebPage

expect = pytest.importorskip(
    "playwright.sync_api", reason="the playwright package is missing (pip install -e '.[test]')"
).expect
EXAMPLE = "shapes-192x128"  # the smallest bundled pair: lite computes it in a fraction of a second
EXAMPLE_DIR = STATIC_DIR / "examples" / EXAMPLE
WIDTH, HEIGHT = 192, 128
RAW_EXAMPLE = "raw-320x240"  # the bundled raw pair, listed with its calibration


def example_bytes(name: str = EXAMPLE) -> tuple[bytes, bytes]:
    folder = STATIC_DIR / "examples" / name
    return (folder / "left.png").read_bytes(), (folder / "right.png").read_bytes()


def served_maps(server: Server, **options: str) -> dict[str, np.ndarray]:
    """The example's maps straight from `POST /disparity?format=json` (the page's reference)."""
    left, right = example_bytes()
    response = httpx.post(
        server.base_url + "/disparity",
        params={"format": "json", **options},
        files={"left": ("left.png", left), "right": ("right.png", right)},
        timeout=60,
    )
    assert response.status_code == 200, response.text
    body = response.json()
    return {
        name: np.frombuffer(base64.b64decode(body[name]["data"]), "<f4").reshape(body[name]["shape"])
        for name in ("disparity", "uncertainty", "depth")
        if body.get(name)
    }


def run_example(web: WebPage, **options: str) -> None:
    """Choose the example pair, fill in `options` (form control id = API option), compute."""
    page = web.page
    page.select_option("#example", EXAMPLE)
    expect(page.locator("#status")).to_contain_text("loaded")
    for name, value in options.items():
        page.fill(f"#{name}", value)
    page.click("#run")
    page.wait_for_selector("#results", state="visible")


@contextmanager
def page_of(browser: Any, server: Server) -> Iterator[Any]:
    """The page of `server` (a server of its own configuration) in a new context, its models listed."""
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    try:
        page = context.new_page()
        page.set_default_timeout(60_000)
        page.goto(server.base_url + "/")
        page.wait_for_selector("#model option", state="attached")
        yield page
    finally:
        context.close()


def hover_pixel(page: Any, canvas_id: str, x: int, y: int, width: int, height: int) -> str:
    """The readout with the mouse over pixel (x, y) of a `width`x`height` map's canvas."""
    canvas = page.locator(f"#{canvas_id}")
    canvas.scroll_into_view_if_needed()
    box = canvas.bounding_box()
    assert box is not None
    canvas.hover(position={"x": (x + 0.5) / width * box["width"], "y": (y + 0.5) / height * box["height"]})
    return str(page.inner_text("#readout"))


def canvas_rgb(web: WebPage, canvas_id: str) -> np.ndarray:
    """The pixels of a canvas of the page, uint8 HxWx3."""
    url = web.page.evaluate("(id) => document.getElementById(id).toDataURL('image/png')", canvas_id)
    png = base64.b64decode(url.removeprefix("data:image/png;base64,"))
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def number(text: str) -> float:
    match = re.search(r"-?\d+(\.\d+)?(e[-+]?\d+)?", text)
    assert match, f"no number in {text!r}"
    return float(match.group())


# --- the page's routes and assets (no browser) ---------------------------------------------------


def test_page_and_static_files_are_served_with_a_strict_policy(default_server: Server) -> None:
    page = httpx.get(default_server.base_url + "/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "default-src 'none'" in page.headers["content-security-policy"]
    assert "connect-src 'self'" in page.headers["content-security-policy"]
    script = httpx.get(default_server.base_url + "/static/app.js")
    assert script.status_code == 200 and script.headers["content-type"].startswith("text/javascript")
    for missing in ("/static/make_assets.py", "/static/nothing.js", "/static/%2e%2e/routes/page.py"):
        answer = httpx.get(default_server.base_url + missing)
        assert answer.status_code == 404, missing
        assert answer.json()["error"]["code"] == "not_found"
    paths = httpx.get(default_server.base_url + "/openapi.json").json()["paths"]
    assert "/" not in paths and not any(path.startswith("/static") for path in paths)


def test_generated_assets_are_current() -> None:
    """colormaps.js is OpenCV's tables (as make_assets.py writes them); examples.json lists real
    pairs of the sizes it says."""
    spec = importlib.util.spec_from_file_location("make_assets", STATIC_DIR / "make_assets.py")
    assert spec is not None and spec.loader is not None
    make_assets = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_assets)
    assert (STATIC_DIR / "colormaps.js").read_text() == make_assets.colormaps_js()
    listing = json.loads((STATIC_DIR / "examples" / "examples.json").read_text())["examples"]
    assert [entry["name"] for entry in listing] == [name for name, *_ in make_assets.EXAMPLES] + [RAW_EXAMPLE]
    assert listing[-1] == make_assets.RAW_EXAMPLE
    for entry in listing:
        for side in ("left", "right"):
            image = cv2.imread(str(STATIC_DIR / entry[side]))
            assert image is not None and image.shape == (entry["height"], entry["width"], 3)
    # the raw example's calibration, served as JSON, is its YAML's rig for images of its size
    raw = listing[-1]
    rig = read_rig(STATIC_DIR / raw["calibration"])
    assert rig.image_size == (raw["width"], raw["height"])
    assert rig.to_json() == read_rig(STATIC_DIR / "examples" / RAW_EXAMPLE / "stereo.yaml").to_json()


# --- in the browser ------------------------------------------------------------------------------


def test_page_loads_without_external_requests(web: WebPage) -> None:
    page, base = web.page, web.server.base_url
    expect(page.locator("#model-info")).to_contain_text("parameters")
    external = [url for url in web.requests if not url.startswith((base + "/", "data:", "blob:"))]
    assert external == []
    requested = {url.removeprefix(base) for url in web.requests}
    assert {
        "/",
        "/static/app.js",
        "/static/style.css",
        "/static/colormaps.js",
        "/models",
        "/static/examples/examples.json",
    } <= requested
    assert page.input_value("#model") == "lite"
    assert page.get_attribute("#iters", "placeholder") == "2,4,6"  # the model's default iterations


def test_example_pair_gives_three_pictures_with_color_bars_in_px(web: WebPage) -> None:
    run_example(web)
    page = web.page
    pictures = {name: canvas_rgb(web, f"{name}-canvas") for name in ("left", "disparity", "uncertainty")}
    for name, rgb in pictures.items():
        assert rgb.shape == (HEIGHT, WIDTH, 3), name
        assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 50, f"{name} is not a picture"
    left = cv2.cvtColor(cv2.imread(str(EXAMPLE_DIR / "left.png")), cv2.COLOR_BGR2RGB)
    assert np.abs(pictures["left"].astype(int) - left).max() <= 2

    maps = served_maps(web.server)
    low, high = robust_range(maps["disparity"])  # the service's own colour range (format=png)
    bar = {part: page.inner_text(f"#disparity-bar .{part}") for part in ("low", "mid", "high")}
    assert all(text.endswith(" px") for text in bar.values()), bar
    assert number(bar["low"]) == pytest.approx(low, rel=5e-3, abs=5e-3)
    assert number(bar["high"]) == pytest.approx(high, rel=5e-3)
    assert number(bar["mid"]) == pytest.approx((low + high) / 2, rel=5e-3)
    assert "1st-99th percentile" in page.inner_text("#disparity-bar .bar-caption")
    assert [page.inner_text(f"#uncertainty-bar .{part}") for part in ("low", "mid", "high")] == ["0", "0.5", "1"]
    # coloured as the service's preview colours it (turbo over the same range)
    expected = colorize(maps["disparity"], low, high, DISPARITY_COLORMAP)
    same = np.all(np.abs(pictures["disparity"].astype(int) - expected) <= 8, axis=2).mean()
    assert same > 0.99
    assert "lite" in page.inner_text("#summary") and "192x128" in page.inner_text("#summary")
    # what the service measured of the rows: the example is rectified exactly
    assert re.search(r"rows on the left's \(within 0\.0\d px\)$", page.inner_text("#summary")), page.inner_text(
        "#summary"
    )
    expect(page.locator("#results")).to_be_in_viewport()  # brought into view below the form


def test_a_ticked_box_sends_its_option_only_where_it_differs_from_the_services_default(web: WebPage) -> None:
    page = web.page
    page.select_option("#example", EXAMPLE)
    expect(page.locator("#status")).to_contain_text("loaded")
    queries = []
    for change in (None, "#flip", "#blend_sgbm", "#refine_edges", "#align_rows"):  # flip off by default, the others on
        if change is not None:
            page.click(change)
        with page.expect_response(lambda answer: "/disparity?" in answer.url) as answer:
            page.click("#run")
        assert answer.value.status == 200
        queries.append(answer.value.url.split("?", 1)[1])
    assert "flip" not in queries[0] and "blend_sgbm" not in queries[0]
    assert "flip=true" in queries[1] and "blend_sgbm" not in queries[1]
    assert "flip=true" in queries[2] and "blend_sgbm=false" in queries[2] and "refine_edges" not in queries[2]
    assert "blend_sgbm=false" in queries[3] and "refine_edges=false" in queries[3]
    assert "align_rows" not in queries[3] and "align_rows=false" in queries[4]


def test_color_range_follows_color_min_and_color_max(web: WebPage) -> None:
    run_example(web, color_min="2", color_max="30")
    assert web.page.inner_text("#disparity-bar .low") == "2 px"
    assert web.page.inner_text("#disparity-bar .high") == "30 px"
    assert "color_min/color_max" in web.page.inner_text("#disparity-bar .bar-caption")


def test_hover_shows_the_value_in_px_and_depth_in_m(web: WebPage) -> None:
    focal_px, baseline_m = 400.0, 0.12
    run_example(web, focal_px=str(focal_px), baseline_m=str(baseline_m))
    maps = served_maps(web.server, focal_px=str(focal_px), baseline_m=str(baseline_m))
    canvas = web.page.locator("#disparity-canvas")
    for target_x, target_y in ((48, 38), (134, 77)):
        canvas.scroll_into_view_if_needed()
        box = canvas.bounding_box()
        assert box is not None  # hover at the pixel's centre on the scaled-up canvas
        canvas.hover(
            position={"x": (target_x + 0.5) / WIDTH * box["width"], "y": (target_y + 0.5) / HEIGHT * box["height"]}
        )
        readout = web.page.inner_text("#readout")
        found = re.search(
            r"x (\d+), y (\d+) · disparity (-?[\d.]+) px · uncertainty ([\d.]+) · "
            r"depth ([\d.e+-]+) m",
            readout,
        )
        assert found, readout
        x, y = int(found.group(1)), int(found.group(2))
        assert (x, y) == (target_x, target_y)
        assert float(found.group(3)) == pytest.approx(maps["disparity"][y, x], abs=0.006)
        assert float(found.group(4)) == pytest.approx(maps["uncertainty"][y, x], abs=6e-4)
        assert float(found.group(5)) == pytest.approx(maps["depth"][y, x], rel=1e-3)
        assert maps["depth"][y, x] == pytest.approx(focal_px * baseline_m / maps["disparity"][y, x], rel=1e-4)


def test_the_summary_says_how_far_the_right_rows_lay_off_and_when_to_check_the_calibration(web: WebPage) -> None:
    page = web.page
    sample = small_dev_sample()  # Tsukuba, as given and with its right image moved 1.5 px down
    height, width = sample.left.shape[:2]
    down = cv2.warpAffine(sample.right, np.float32([[1, 0, 0], [0, 1, 1.5]]), (width, height))
    page.fill("#iters", "1,1,1")
    bare = np.repeat(np.linspace(40, 220, width, dtype=np.float32)[None, :, None], 3, 2)  # no corner to track
    bare = np.repeat(bare, height, 0).astype(np.uint8)
    said = {
        "rows off the left's by up to 1.": (sample.left, down),
        "rows on the left's (within 0.": (sample.left, sample.right),
        "rows: too little texture to measure their offset": (bare, bare),
    }
    for words, (left, right) in said.items():
        for side, image in (("left", left), ("right", right)):
            png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1].tobytes()
            page.set_input_files(
                f"#{side}-file", files=[{"name": f"{side}.png", "mimeType": "image/png", "buffer": png}]
            )
        page.click("#run")
        expect(page.locator("#summary")).to_contain_text(words)
        advice = "(check the rig's calibration)" in page.inner_text("#summary")
        assert advice == (right is down), page.inner_text("#summary")  # 1.5 px: a pixel or more


def choose_raw_pair(page) -> None:
    """Put the raw pair of tests/raw_camera.py (its left and right views, as PNGs) in the page's
    left and right file fields."""
    left, right = (
        np.clip(view, 0, 255).astype(np.uint8)
        for view in (raw_view(K1, D1, np.eye(3), np.zeros(3)), raw_view(K2, D2, R, T))
    )
    for side, image in (("left", left), ("right", right)):
        png = cv2.imencode(".png", image)[1].tobytes()
        page.set_input_files(f"#{side}-file", files=[{"name": f"{side}.png", "mimeType": "image/png", "buffer": png}])


def test_a_raw_pair_with_its_calibration_file_gives_depth_on_the_cameras_pixels(web: WebPage, tmp_path: Path) -> None:
    page = web.page
    choose_raw_pair(page)
    bad = opencv_file(tmp_path / "bad.yaml", T=np.zeros(3))
    page.set_input_files("#calibration-file", str(bad))
    page.click("#run")
    page.wait_for_selector("#error", state="visible")
    assert page.inner_text("#error").startswith("422 invalid_calibration: calibration `T`")

    page.set_input_files("#calibration-file", str(opencv_file(tmp_path / "stereo.yaml")))
    page.select_option("#frame", "original")
    page.click("#run")
    page.wait_for_selector("#results", state="visible")
    assert "raw pair, rectified by its calibration" in page.inner_text("#summary")
    assert "maps in the original left image" in page.inner_text("#summary")
    assert page.is_enabled("#download-list button[data-format=depth_png16]")
    canvas = page.locator("#disparity-canvas")
    canvas.scroll_into_view_if_needed()
    box = canvas.bounding_box()
    assert box is not None
    readouts = {}
    for name, (x, y) in {"plane": (160, 120), "corner": (1, 1)}.items():
        canvas.hover(position={"x": (x + 0.5) / RAW_WIDTH * box["width"], "y": (y + 0.5) / RAW_HEIGHT * box["height"]})
        readouts[name] = page.inner_text("#readout")
    depth = re.search(r"depth ([\d.e+-]+) m", readouts["plane"])
    assert depth, readouts["plane"]
    assert float(depth.group(1)) == pytest.approx(PLANE_Z, rel=0.08)
    assert "no value: outside the rectified image" in readouts["corner"]


def run_url(page: Any) -> str:
    """Click Run; the URL of the `POST /disparity` the page then sends."""
    with page.expect_response(lambda answer: "/disparity?" in answer.url) as answer:
        page.click("#run")
    return str(answer.value.url)


def test_a_raw_pairs_maps_line_up_with_the_left_image_shown_unless_rectified_is_chosen(
    web: WebPage, tmp_path: Path
) -> None:
    """With a calibration the page asks for the maps in the left image's own pixels (frame=original),
    the image it draws; where the user chooses frame=rectified the left panel says it does not line
    up, and hovering it reads no map value."""
    page = web.page
    choose_raw_pair(page)
    page.set_input_files("#calibration-file", str(opencv_file(tmp_path / "stereo.yaml")))
    page.fill("#iters", "1,1,1")
    assert "frame=original" in run_url(page)
    expect(page.locator("#summary")).to_contain_text("maps in the original left image")
    assert page.inner_text("#left-caption") == "Left image"
    expect(page.locator("#left-note")).to_be_hidden()
    # the left panel's pixel reads what the maps hold there
    readout = hover_pixel(page, "left-canvas", 160, 120, RAW_WIDTH, RAW_HEIGHT)
    assert re.match(r"x 1[56]\d, y 1[12]\d · disparity ", readout), readout
    assert readout == hover_pixel(page, "disparity-canvas", 160, 120, RAW_WIDTH, RAW_HEIGHT)

    page.select_option("#frame", "rectified")
    assert "frame=rectified" in run_url(page)
    expect(page.locator("#summary")).to_contain_text("maps in the rectified left image")
    assert page.inner_text("#left-caption") == "Left image (not rectified)"
    expect(page.locator("#left-note")).to_contain_text("they do not line up with it")
    readout = hover_pixel(page, "left-canvas", 160, 120, RAW_WIDTH, RAW_HEIGHT)
    assert "disparity" not in readout and "hover over a map" in readout
    assert "disparity" in hover_pixel(page, "disparity-canvas", 160, 120, RAW_WIDTH, RAW_HEIGHT)


def test_the_raw_example_brings_its_calibration_and_gives_its_true_depth(web: WebPage) -> None:
    page = web.page
    page.select_option("#example", RAW_EXAMPLE)
    expect(page.locator("#status")).to_contain_text("with its calibration stereo.json")
    assert page.evaluate("document.getElementById('calibration-file').files[0].name") == "stereo.json"
    page.fill("#iters", "2,2,4")
    page.click("#run")
    page.wait_for_selector("#results", state="visible")
    summary = page.inner_text("#summary")
    assert "raw pair, rectified by its calibration" in summary and "maps in the original left image" in summary
    truth = cv2.imread(str(STATIC_DIR / "examples" / RAW_EXAMPLE / "depth_mm.png"), cv2.IMREAD_UNCHANGED) / 1000.0
    for x, y in ((100, 120), (220, 80), (160, 200)):
        readout = hover_pixel(page, "disparity-canvas", x, y, 320, 240)
        depth = re.search(r"depth ([\d.e+-]+) m", readout)
        assert depth, readout
        assert float(depth.group(1)) == pytest.approx(truth[y, x], rel=0.1), (x, y)

    # a rectified example, or the user's own files, leave the example's calibration behind
    page.select_option("#example", EXAMPLE)
    expect(page.locator("#status")).to_contain_text(f"example {EXAMPLE} loaded")
    assert page.evaluate("document.getElementById('calibration-file').files.length") == 0
    page.select_option("#example", RAW_EXAMPLE)
    expect(page.locator("#status")).to_contain_text("with its calibration")
    left, right = example_bytes()
    for side, data in (("left", left), ("right", right)):
        page.set_input_files(f"#{side}-file", files=[{"name": f"{side}.png", "mimeType": "image/png", "buffer": data}])
    assert page.evaluate("document.getElementById('calibration-file').files.length") == 0
    page.click("#run")
    expect(page.locator("#summary")).to_contain_text("192x128")
    assert "raw pair" not in page.inner_text("#summary")


def test_every_format_downloads(web: WebPage, tmp_path: Path) -> None:
    run_example(web)
    page = web.page
    offered = page.eval_on_selector_all("#download-list button", "buttons => buttons.map(b => b.dataset.format)")
    assert sorted(offered) == sorted(fmt.value for fmt in OutputFormat)
    assert page.is_disabled("#download-list button[data-format=depth_png16]")  # no calibration given
    maps = served_maps(web.server)
    saved = {}
    for fmt in ("json", "npz", "png", "disparity_png16", "ply"):
        with page.expect_download() as download:
            page.click(f"#download-list button[data-format={fmt}]")
        path = tmp_path / download.value.suggested_filename
        download.value.save_as(path)
        saved[fmt] = path
    assert saved["npz"].name == f"{EXAMPLE}_maps.npz"
    with np.load(saved["npz"]) as archive:
        np.testing.assert_allclose(archive["disparity"], maps["disparity"], atol=1e-4)
    body = json.loads(saved["json"].read_text())
    assert body["image_size"] == {"width": WIDTH, "height": HEIGHT}
    preview = cv2.imread(str(saved["png"]))
    assert preview is not None and preview.shape[1] == 2 * WIDTH + PREVIEW_GAP
    kitti = cv2.imread(str(saved["disparity_png16"]), cv2.IMREAD_UNCHANGED)
    assert kitti.dtype == np.uint16 and kitti.shape == (HEIGHT, WIDTH)
    assert saved["ply"].read_bytes().startswith(b"ply\nformat binary_little_endian")
    assert web.page.is_hidden("#error")


def test_two_dropped_files_become_the_pair(web: WebPage) -> None:
    """Dropping both files on one zone: the one named `right...` goes right."""
    page = web.page
    transfer = page.evaluate_handle("""async () => {
        const transfer = new DataTransfer();
        for (const side of ['right', 'left']) {
            const blob = await (await fetch(`static/examples/shapes-192x128/${side}.png`)).blob();
            transfer.items.add(new File([blob], `${side}_view.png`, {type: 'image/png'}));
        }
        return transfer;
    }""")
    page.dispatch_event("#left-drop", "drop", {"dataTransfer": transfer})
    assert page.inner_text("#left-name") == "left_view.png"
    assert page.inner_text("#right-name") == "right_view.png"
    page.click("#run")
    page.wait_for_selector("#results", state="visible")
    assert page.inner_text("#disparity-bar .high").endswith(" px")


@pytest.mark.parametrize("case", ["text_file", "size_mismatch", "bad_option"])
def test_bad_upload_shows_the_services_error(web: WebPage, case: str) -> None:
    page = web.page
    left, right = example_bytes()
    if case == "text_file":
        left_file = {"name": "notes.txt", "mimeType": "text/plain", "buffer": b"not an image\n"}
        expected = "415 unsupported_media_type: left: not a PNG, JPEG, BMP or TIFF file"
    elif case == "size_mismatch":
        left_file = {"name": "left.png", "mimeType": "image/png", "buffer": left}
        right = example_bytes("shapes-288x192")[1]
        expected = "422 size_mismatch: left is 192x128 but right is 288x192"
    else:
        left_file = {"name": "left.png", "mimeType": "image/png", "buffer": left}
        page.fill("#scale", "2")
        expected = "422 invalid_request: query.scale"
    page.set_input_files("#left-file", files=[left_file])
    page.set_input_files("#right-file", files=[{"name": "right.png", "mimeType": "image/png", "buffer": right}])
    page.click("#run")
    page.wait_for_selector("#error", state="visible")
    assert page.inner_text("#error").startswith(expected)
    assert page.is_hidden("#results")
    assert page.is_enabled("#run")


def test_missing_image_is_said_before_sending(web: WebPage) -> None:
    page = web.page
    page.click("#run")
    page.wait_for_selector("#error", state="visible")
    assert "choose a left and a right image" in page.inner_text("#error")
    assert not any(url.endswith("/disparity") or "/disparity?" in url for url in web.requests)


@pytest.mark.slow
def test_choosing_an_untrained_model_shows_a_warning(browser: Any, tmp_path: Path) -> None:
    weights = f"full={write_untrained(tmp_path / 'full.pt')}"
    with run_uvicorn(tmp_path, models="lite,full", weights=weights) as server, page_of(browser, server) as page:
        page.wait_for_selector("#model option[value=full]", state="attached")
        warning = page.locator("#model-warning")
        expect(warning).to_be_hidden()  # lite, the default, is trained
        page.select_option("#model", "full")
        expect(warning).to_be_visible()
        expect(warning).to_contain_text("full is untrained")
        expect(warning).to_contain_text("Choose a trained model (lite) for real results.")
        expect(page.locator("#model option[value=full]")).to_contain_text("untrained")
        page.select_option("#model", "lite")
        expect(warning).to_be_hidden()


@pytest.mark.slow
def test_with_only_untrained_weights_the_page_says_no_trained_model_is_loaded_and_the_result_says_untrained(
    browser: Any, tmp_path: Path
) -> None:
    untrained = write_untrained(tmp_path / "lite.pt", name="lite")
    with run_uvicorn(tmp_path, models="lite", weights=f"lite={untrained}") as server, page_of(browser, server) as page:
        warning = page.locator("#model-warning")
        expect(warning).to_contain_text("lite is untrained")
        expect(warning).to_contain_text("No trained model is loaded on this server")
        expect(warning).not_to_contain_text("Choose a trained model")
        page.select_option("#example", EXAMPLE)
        expect(page.locator("#status")).to_contain_text("loaded")
        page.fill("#iters", "1,1,1")
        page.click("#run")
        page.wait_for_selector("#results", state="visible")
        expect(page.locator("#summary")).to_contain_text("lite (untrained: maps not usable), weights ")
        result_warning = page.locator("#result-warning")
        expect(result_warning).to_be_visible()
        expect(result_warning).to_contain_text("lite is untrained")
        expect(result_warning).to_contain_text("No trained model is loaded on this server")


@pytest.mark.slow
def test_full_is_marked_as_not_the_recommended_model_wherever_the_page_shows_it(browser: Any, tmp_path: Path) -> None:
    """The bundled full (trained, status `trained`) is slower and no more accurate than lite: the
    model list, its description and its results say so, and no model shows its own training
    validation's dev numbers (each model's at another time: not comparable)."""
    with run_uvicorn(tmp_path, models="lite,full", backend="torch") as server, page_of(browser, server) as page:
        page.wait_for_selector("#model option[value=full]", state="attached")
        assert "not recommended" in page.inner_text("#model option[value=full]")
        assert "not recommended" not in page.inner_text("#model option[value=lite]")
        warning = page.locator("#model-warning")
        expect(warning).to_be_hidden()  # lite, the default
        assert "EPE" not in page.inner_text("#model-info")
        page.select_option("#model", "full")
        expect(warning).to_be_visible()
        expect(warning).to_contain_text("full is not the recommended model")
        expect(warning).to_contain_text("no more accurate than lite")
        expect(warning).to_contain_text("Use lite.")
        assert "EPE" not in page.inner_text("#model-info")
        page.select_option("#example", EXAMPLE)
        expect(page.locator("#status")).to_contain_text("loaded")
        page.fill("#iters", "1,1,1")
        page.click("#run")
        page.wait_for_selector("#results", state="visible")
        assert page.inner_text("#summary").startswith("full, weights ")
        expect(page.locator("#result-warning")).to_contain_text("full is not the recommended model")
        page.select_option("#model", "lite")
        expect(warning).to_be_hidden()
        page.click("#run")
        expect(page.locator("#summary")).to_contain_text("lite, weights ")
        expect(page.locator("#result-warning")).to_be_hidden()


def test_at_420_px_wide_no_word_of_the_page_breaks_across_lines(web: WebPage) -> None:
    page = web.page
    page.set_viewport_size({"width": 420, "height": 900})
    split = page.evaluate(
        """() => {
          const split = [];
          const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
          for (let node = walker.nextNode(); node; node = walker.nextNode()) {
            if (!node.parentElement.offsetParent) continue;  // not shown
            for (const match of node.textContent.matchAll(/\\S+/g)) {
              const range = document.createRange();
              range.setStart(node, match.index);
              range.setEnd(node, match.index + match[0].length);
              const lines = new Set([...range.getClientRects()].map((rect) => Math.round(rect.top)));
              if (lines.size > 1) split.push(match[0]);
            }
          }
          return split;
        }"""
    )
    assert split == []
