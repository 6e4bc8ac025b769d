"""Spec of the OpenVINO backend: the same maps as torch for every knob, never a stalled call nor
an export that was not asked for, a disk cache that spares a restart the export, exports that end
with their process and leave no partial file, and an honest choice of backend and precision.

The graphs here run one iteration per stage: an export costs CPU time in proportion to the
iterations it unrolls, and the equality of the maps does not depend on their number.
"""

import contextlib
import ctypes
import io
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crestereo_pp.cli.main import main
from crestereo_pp.inference import load_model
from crestereo_pp.inference.backend_choice import resolve_backend, resolve_precision
from crestereo_pp.inference.openvino_backend import (
    MAX_BLOB_CACHE_BYTES,
    MAX_COMPILED_BYTES,
    compiled_bytes,
    native_bf16,
    prune_oldest,
)
from crestereo_pp.inference.two_pass import (
    ENLARGEMENTS,
    MAX_ENLARGED_PIXELS,
    large_disparity_percentile,
    largest_enlargement,
    way_maps,
)
from crestereo_pp.model.config import ModelConfig
from crestereo_pp.model.network import padded_size
from shared_data import STEREO_DEV

REPO = Path(__file__).resolve().parents[2]

ITERS = (1, 1, 1)
PAIR = STEREO_DEV / "middlebury2001_tsukuba"  # 384x288, the smallest real pair
NATIVE_BF16_ONLY = pytest.mark.skipif(not native_bf16(), reason="needs a CPU that computes bf16 natively")


@pytest.fixture(scope="module")
def tsukuba():
    if not PAIR.is_dir():
        pytest.skip(f"the real pairs are not at {STEREO_DEV}")
    left, right = (cv2.imread(str(PAIR / name))[..., ::-1].copy() for name in ("left.png", "right.png"))
    return left, right


@pytest.fixture(scope="module")
def cache_dir(openvino_cache):
    return openvino_cache


@pytest.fixture(scope="module")
def torch_lite():
    return load_model("lite", backend="torch")


class Messages(logging.Handler):
    """The messages logged to one logger while attached."""

    def __init__(self) -> None:
        super().__init__(level=logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture(scope="module")
def first_call(cache_dir, tsukuba, tmp_path_factory):
    """An OpenVINO predictor with an empty cache and its first call (before any graph exists);
    then a command asked to run OpenVINO at the same iterations, which exports the graphs for cold
    and warm starts (one export serves every spec here: each takes a core for half a minute), and
    what it printed and logged."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
        predictor = load_model("lite", backend="openvino", precision="fp32")
        before = predictor.predict(*tsukuba, iters=ITERS)
        counts = (predictor.openvino.runs, predictor.openvino.fallback_runs, predictor.openvino.exports)
        exporting = [thread.name for thread in threading.enumerate() if thread.name == "openvino-export"]
        output = tmp_path_factory.mktemp("predict") / "d.pfm"
        arguments = [str(PAIR / "left.png"), str(PAIR / "right.png"), "-o", str(output)]
        options = ["--backend", "openvino", "--precision", "fp32", "--iters", *map(str, ITERS), "--two-pass", "on"]
        logger, messages = logging.getLogger("crestereo_pp.inference.openvino_backend"), Messages()
        logger.addHandler(messages)
        logger.setLevel(logging.INFO)
        try:
            with contextlib.redirect_stderr(io.StringIO()) as printed:
                assert main(["predict", *arguments, *options]) == 0
        finally:
            logger.removeHandler(messages)
            logger.setLevel(logging.NOTSET)
    command = Command(printed.getvalue(), messages.messages, output)
    return predictor, before, command, (*counts, exporting)


@dataclass(frozen=True)
class Command:
    """What `crestereo-pp predict --backend openvino` printed (stderr), logged and wrote."""

    err: str
    log: list[str]
    output: Path


def assert_maps_agree(actual, expected) -> None:
    """OpenVINO f32 against torch: float rounding only (0.0004 px seen at most on real pairs)."""
    for name in ("disparity", "uncertainty"):
        a, e = (np.asarray(getattr(maps, name), np.float64) for maps in (actual, expected))
        assert a.shape == e.shape
        assert np.abs(a - e).max() < 0.01, (name, np.abs(a - e).max())


def test_a_call_whose_graph_is_not_prepared_runs_on_torch_and_starts_no_export(first_call, torch_lite, tsukuba):
    predictor, before, _, (runs, fallback_runs, exports, exporting) = first_call
    assert (runs, fallback_runs, exports, exporting) == (0, 2, 0, [])  # auto's quick pass, then the pass
    expected = torch_lite.predict(*tsukuba, iters=ITERS)
    np.testing.assert_array_equal(before.disparity, expected.disparity)  # torch itself computed it


def test_a_command_asked_to_run_openvino_exports_its_missing_graphs_side_by_side_into_the_cache_saying_so_once(
    first_call,
):
    predictor, _, command, _ = first_call
    assert command.err.count("exporting lite's OpenVINO graphs") == 1 and "running on torch" not in command.err
    log = "\n".join(command.log)
    # one graph per iterations, cold and warm alike; a warm start's second pass runs the 1/4 stage alone
    for counts in ("1, 1, 1", "0, 0, 1"):
        assert f"exporting the graph for iterations ({counts})" in log
        assert re.search(rf"iterations \({counts}\) is ready, exported in \d+ s", log), log
    started = [i for i, m in enumerate(command.log) if m.startswith("openvino: exporting the graph")]
    ended = [i for i, m in enumerate(command.log) if "exported in" in m]
    assert len(started) == len(ended) == 2 and max(started) < min(ended), log  # both under way at once
    files = {path.name for path in predictor.openvino.graph_dir.iterdir()}
    assert files == {f"iters{counts}.{suffix}" for counts in ("1-1-1", "0-0-1") for suffix in ("xml", "bin")}
    assert command.output.is_file()


def test_the_cli_runs_openvino_where_the_graphs_are_cached_and_else_torch_exporting_nothing(
    first_call, cache_dir, tmp_path, monkeypatch, capsys
):
    monkeypatch.delenv("CRESTEREO_BACKEND")  # auto
    monkeypatch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
    data = tmp_path / "pairs"
    data.mkdir()
    (data / PAIR.name).symlink_to(PAIR)
    graphs = set(cache_dir.rglob("*.xml"))
    for finest, backend in ((1, "openvino"), (2, "torch")):
        arguments = ["eval", str(data), "--iters", "1", "1", str(finest), "--two-pass", "off", "--precision", "fp32"]
        assert main(arguments) == 0
        out, err = capsys.readouterr()
        assert f"lite on {backend}, fp32" in out
        assert ("computing on torch" in err) == (backend == "torch"), err
    assert set(cache_dir.rglob("*.xml")) == graphs  # nothing exported


def test_prepare_says_which_graphs_are_in_the_cache_already(first_call, cache_dir, monkeypatch, capsys):
    monkeypatch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
    assert main(["prepare", "--iters", "1", "1", "1"]) == 0
    out = capsys.readouterr().out
    for counts, use in (
        ("1, 1, 1", "cold starts and a sequence's warm frames"),
        ("0, 0, 1", "the second of two passes"),
    ):
        assert f"lite's graph for iterations ({counts}) ({use}): in the cache already" in out
    assert "exporting" not in out


def test_prepare_prunes_only_where_asked_the_graphs_of_other_versions_and_keeps_other_weights(
    first_call, cache_dir, monkeypatch, capsys
):
    monkeypatch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
    current = first_call[0].openvino.graph_dir
    version = current.name.split("-torch", 1)[1]  # this install's torch and export versions
    older_export = current.with_name(current.name.rsplit("-v", 1)[0] + "-v7")
    older_torch = current.with_name(f"lite-{'0' * 16}-torch2.12.0+cpu-v8")
    own_weights = current.with_name(f"lite-{'ab' * 8}-torch{version}")
    for folder in (older_export, older_torch, own_weights):
        folder.mkdir()
        (folder / "iters1-1-1.bin").write_bytes(bytes(1_500_000))
    try:
        assert main(["prepare", "--iters", "1", "1", "1"]) == 0
        out = capsys.readouterr().out
        assert "2 graph folders of other torch or export versions in the cache" in out
        assert "(3 MB): --prune removes them" in out
        assert older_export.is_dir() and older_torch.is_dir()
        assert main(["prepare", "--iters", "1", "1", "1", "--prune"]) == 0
        assert "removed 2 graph folders of other torch or export versions (3 MB)" in capsys.readouterr().out
        assert not older_export.exists() and not older_torch.exists()
        assert own_weights.is_dir() and current.is_dir() and (cache_dir / "openvino" / "compiled").is_dir()
        assert main(["prepare", "--iters", "1", "1", "1"]) == 0
        assert "other torch or export versions" not in capsys.readouterr().out
    finally:
        shutil.rmtree(own_weights, ignore_errors=True)


def test_load_model_reads_the_graphs_it_is_asked_to_prepare_from_the_cache(first_call, cache_dir):
    loaded = load_model("lite", backend="openvino", precision="fp32", cache_dir=cache_dir, prepare_iters=[ITERS])
    assert loaded.ready(ITERS) and loaded.ready(ITERS, warm_start=True) and loaded.openvino.exports == 0


def test_the_partial_files_of_an_export_whose_process_ended_are_removed(tmp_path, openvino_cache):
    # openvino_cache only orders this test with the others that run OpenVINO here (tests/conftest.py)
    predictor = load_model("lite", backend="openvino", cache_dir=tmp_path)
    graph_dir = predictor.openvino.graph_dir
    graph_dir.mkdir(parents=True)
    ended = subprocess.Popen(["true"])
    ended.wait()
    abandoned = [graph_dir / f".{ended.pid}-0123abcd-iters1-1-1.{suffix}" for suffix in ("xml", "bin")]
    under_way = graph_dir / f".{os.getpid()}-4567cdef-iters0-0-1.xml"
    for path in (*abandoned, under_way):
        path.write_text("partial")
    load_model("lite", backend="openvino", cache_dir=tmp_path)
    assert list(graph_dir.iterdir()) == [under_way]


@pytest.mark.slow
def test_an_export_ends_with_the_process_that_asked_for_it_and_leaves_no_file(tmp_path):
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    environment = {**os.environ, "CRESTEREO_CACHE_DIR": str(tmp_path / "cache"), "TMPDIR": str(temporary)}
    script = "from crestereo_pp.inference import load_model; load_model('lite', backend='openvino').prepare((1, 1, 1))"
    parent = subprocess.Popen([sys.executable, "-c", script], env=environment, cwd=REPO)
    try:
        child = wait_for(lambda: export_child(parent.pid), timeout_s=120)
        # exporting: the child imports openvino once it is set to end with its parent
        wait_for(lambda: "libopenvino" in Path(f"/proc/{child}/maps").read_text(), timeout_s=120)
        parent.send_signal(signal.SIGTERM)
        assert parent.wait(timeout=30) == -signal.SIGTERM
        wait_for(lambda: not running(child), timeout_s=30)
    finally:
        parent.kill()
    assert [path.name for path in (tmp_path / "cache").rglob("*") if path.is_file()] == []
    assert list(temporary.iterdir()) == []


def export_child(parent: int) -> int | None:
    """The pid of `parent`'s export process, once it runs."""
    for task in Path(f"/proc/{parent}/task").iterdir():
        for pid in (task / "children").read_text().split():
            if b"crestereo_pp.inference.openvino_export" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return int(pid)
    return None


def proc_status(pid: int) -> dict[str, str]:
    lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    return dict(line.split(":\t", 1) for line in lines if ":\t" in line)


def running(pid: int) -> bool:
    """Whether `pid` is a process that has not ended (a zombie has ended)."""
    try:
        return not proc_status(pid)["State"].startswith("Z")
    except FileNotFoundError:
        return False


def wait_for(condition, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        assert time.monotonic() < deadline, f"not within {timeout_s} s"
        time.sleep(0.1)
    return value


def test_openvino_maps_equal_torch_maps_on_a_real_pair_for_every_knob(first_call, torch_lite, tsukuba):
    predictor, *_ = first_call
    left, right = tsukuba
    runs = predictor.openvino.runs
    for options in (
        {},
        {"two_pass": True},
        {"two_pass": False},
        {"scale": 0.5},
        {"raw_uncertainty": True},
        {"init_disparity": torch_lite.predict(left, right, iters=ITERS).disparity},
    ):
        assert_maps_agree(
            predictor.predict(left, right, iters=ITERS, **options),
            torch_lite.predict(left, right, iters=ITERS, **options),
        )
    # A batch of two sizes of one padded shape (288 x 384), padded to it as torch pads it.
    lefts, rights = [left, left[:270, :370]], [right, right[:270, :370]]
    for actual, expected in zip(
        predictor.predict_batch(lefts, rights, iters=ITERS, two_pass=False),
        torch_lite.predict_batch(lefts, rights, iters=ITERS, two_pass=False),
        strict=True,
    ):
        assert_maps_agree(actual, expected)
    # auto (the default) runs a quick pass first, two_pass=True a half-resolution one, a warm start one
    # pass; at scale 0.5 (144 x 192 px) auto takes one pass without a quick one
    assert predictor.openvino.runs - runs == 2 + 2 + 1 + 1 + 2 + 1 + 1 and predictor.openvino.fallback_runs == 2


def test_a_restart_reads_its_graphs_from_the_disk_cache_without_exporting(first_call, cache_dir, tsukuba):
    assert any(cache_dir.rglob("*.xml")) and any((cache_dir / "openvino" / "compiled").iterdir())
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CRESTEREO_CACHE_DIR", str(cache_dir))
        restarted = load_model("lite", backend="openvino", precision="fp32")
    restarted.predict(*tsukuba, iters=ITERS)
    # auto's quick pass and the pass, both compiled from the cache
    assert (restarted.openvino.runs, restarted.openvino.fallback_runs, restarted.openvino.exports) == (2, 0, 0)


LET_GO_IN_ORDER_THEN_INTERRUPTED = """
import gc, signal
import numpy as np
# Python's own Ctrl-C handler, as at a terminal: a Python started with SIGINT ignored (a background
# job of a script, as the suite may be) installs none and inherits the ignoring
signal.signal(signal.SIGINT, signal.default_int_handler)
from crestereo_pp.inference import load_model
image = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
models = [load_model("lite", backend="openvino", precision="fp32") for _ in range(2)]
for index in range(2):
    assert models[index].ready((1, 1, 1))
    models[index].predict(image, image, iters=(1, 1, 1))  # compiled
while models:
    models.pop(0)  # let go in the order they were made, as a notebook that loads a model again
    gc.collect()
try:
    # Ctrl-C, on this (the main) thread, where the models lived
    signal.raise_signal(signal.SIGINT)
except KeyboardInterrupt:
    print("interrupted")
"""


def test_ctrl_c_after_models_were_let_go_in_the_order_they_were_made_is_a_keyboard_interrupt(first_call, cache_dir):
    environment = {**os.environ, "CRESTEREO_CACHE_DIR": str(cache_dir)}
    script = [sys.executable, "-c", LET_GO_IN_ORDER_THEN_INTERRUPTED]
    done = subprocess.run(script, env=environment, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert (done.returncode, done.stdout) == (0, "interrupted\n"), done.stderr[-2000:]


def test_whether_a_graph_is_ready_is_answered_at_once_while_a_compile_holds_the_backend(first_call, cache_dir):
    predictor, *_ = first_call
    backend = predictor.openvino
    answers: list[tuple[bool, bool]] = []
    with backend._lock:  # what compiling a new shape holds for seconds
        asking = threading.Thread(target=lambda: answers.append((backend.ready(ITERS), backend.ready((1, 1, 5)))))
        asking.start()
        asking.join(timeout=5)
        assert not asking.is_alive(), "ready() waited for the compile"
    assert answers == [(True, False)]  # 1,1,1 exported by the command above; 1,1,5 never


def test_compiled_shapes_are_kept_up_to_a_bound_least_recently_used_first(first_call, tsukuba):
    predictor, *_ = first_call
    backend = predictor.openvino
    backend.max_shapes = 2
    left, right = tsukuba
    for height in (64, 96, 128):  # three padded shapes
        predictor.predict(left[:height, :128], right[:height, :128], iters=ITERS, two_pass=False)
    assert len(backend.compiled) == 2
    assert [key[1][2] for key in backend.compiled] == [96, 128]


def test_compiled_shapes_are_kept_within_their_estimated_memory_and_the_estimate_is_not_below_it(first_call, tsukuba):
    predictor, *_ = first_call
    backend = predictor.openvino
    left, right = tsukuba
    shapes = [(1, 3, height, 128) for height in (64, 96, 128)]
    backend.compiled.clear()
    backend.max_shapes, backend.max_bytes = (
        8,
        sum(compiled_bytes(ITERS, shape, False, backend.channels) for shape in shapes[1:]),
    )
    try:
        in_use = [malloc_in_use()]
        for _, _, height, width in shapes:
            predictor.predict(left[:height, :width], right[:height, :width], iters=ITERS, two_pass=False)
            in_use.append(malloc_in_use())
        # room is made before compiling: the first shape went for the third, and the bound held throughout
        assert [shape for _, shape, _ in backend.compiled] == shapes[1:]
        assert backend.kept_bytes <= backend.max_bytes
        # what the first two shapes really took (nothing was dropped yet) is within their estimates
        for shape, before, after in zip(shapes[:2], in_use, in_use[1:], strict=False):
            assert 0 < after - before <= compiled_bytes(ITERS, shape, False, backend.channels), (shape, after - before)
        backend.max_bytes = 1  # a shape over the whole bound is kept, alone
        predictor.predict(left[:64, :128], right[:64, :128], iters=ITERS, two_pass=False)
        assert [shape for _, shape, _ in backend.compiled] == shapes[:1]
    finally:
        backend.max_shapes, backend.max_bytes = 8, MAX_COMPILED_BYTES


@pytest.mark.parametrize("bf16", [False, pytest.param(True, marks=NATIVE_BF16_ONLY)])
def test_the_estimate_of_a_large_compiled_shape_is_not_below_what_it_takes(first_call, tsukuba, bf16):
    """Where the image's buffers outweigh the graph (1x3x384x640: about three quarters of the
    estimate), in the precision it is compiled for."""
    predictor, *_ = first_call
    backend = predictor.openvino
    shape = (1, 3, 384, 640)
    backend.compiled.clear()
    left, right = (torch.rand(shape) * 255 for _ in range(2))
    before = malloc_in_use()
    backend(left, right, None, ITERS, bf16)
    taken = malloc_in_use() - before
    backend.compiled.clear()
    estimate = compiled_bytes(ITERS, shape, bf16, backend.channels)
    assert estimate * 0.6 < taken <= estimate, (taken, estimate)


def test_the_compiled_shapes_bound_holds_every_shape_of_a_cameras_pairs_at_lites_largest_enlargement():
    """The shapes ``two_pass="auto"`` compiles for one camera's pairs at the largest size it
    enlarges to (quick pass, one pass, the half and refining passes of two) fit in the bound
    together for lite, in either precision; under a smaller one they evict one another and every
    request compiles again. (full, with four times the channels, needs about three times as much:
    service/README.md, "Backends".)"""
    shapes: set[tuple[tuple[int, int, int], tuple[int, int, int, int]]] = set()

    def forward(left, right, iters, init):  # records what OpenVINO would compile, padded as it pads
        batch, _, height, width = left.shape
        shapes.add((tuple(iters), (batch, 3, padded_size(height), padded_size(width))))
        return torch.zeros(batch, 1, height, width), torch.zeros(batch, 1, height, width)

    config = ModelConfig.preset("lite")
    iters = config.iters
    pair = torch.zeros(1, 3, 600, 888)  # 1.5x is just within MAX_ENLARGED_PIXELS
    factor = largest_enlargement(600, 888)
    assert factor == max(ENLARGEMENTS) and 600 * 888 * factor**2 > 0.99 * MAX_ENLARGED_PIXELS
    large_disparity_percentile(pair, pair, iters, forward)
    for two_passes in (False, True):
        way_maps(pair, pair, iters, (two_passes, factor), forward)
    assert len(shapes) == 4
    for bf16 in (True, False):
        assert (
            sum(compiled_bytes(graph, shape, bf16, config.feature_dim) for graph, shape in shapes) <= MAX_COMPILED_BYTES
        )


def test_the_disk_cache_of_compiled_shapes_keeps_within_its_bound_dropping_the_oldest(first_call, tsukuba):
    predictor, *_ = first_call
    backend = predictor.openvino
    left, right = tsukuba
    assert backend.blob_dir is not None
    backend.compiled.clear()
    backend.max_blob_bytes = 1  # room for no blob but the one being compiled
    try:
        for width in (160, 192):  # two shapes this module compiles nowhere else
            predictor.predict(left[:64, :width], right[:64, :width], iters=ITERS, two_pass=False)
            blobs = list(backend.blob_dir.glob("*.blob"))
            assert len(blobs) == 1, blobs  # the others went before the compile; this one is new
        newest = blobs[0]
        assert newest.stat().st_size > 0
    finally:
        backend.max_blob_bytes = MAX_BLOB_CACHE_BYTES


def test_pruning_a_folder_deletes_the_least_recently_modified_files_until_the_rest_fit(tmp_path):
    for age, name in enumerate(["newest", "middle", "oldest"]):
        path = tmp_path / f"{name}.blob"
        path.write_bytes(b"x" * 100)
        os.utime(path, (1_000_000 - age, 1_000_000 - age))
    (tmp_path / "other.txt").write_bytes(b"y" * 1000)  # not matched: never counted nor deleted
    assert prune_oldest(tmp_path, "*.blob", 250) == 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["middle.blob", "newest.blob", "other.txt"]
    assert prune_oldest(tmp_path, "*.blob", 200) == 0
    assert prune_oldest(tmp_path, "*.blob", 0) == 200
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.txt"]


def malloc_in_use() -> int:
    """Bytes glibc's malloc has handed out and not had back (mallinfo2: arenas and mmapped chunks)."""
    fields = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")

    class MallInfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in fields]

    mallinfo2 = ctypes.CDLL(None).mallinfo2
    mallinfo2.restype = MallInfo2
    info = mallinfo2()
    return int(info.uordblks + info.hblkhd)


def test_bf16_moves_the_maps_a_little_and_runs_only_where_asked(first_call, tsukuba):
    predictor, *_ = first_call
    fp32 = predictor.predict(*tsukuba, iters=ITERS)
    predictor.precision = "bf16"
    try:
        bf16 = predictor.predict(*tsukuba, iters=ITERS)
    finally:
        predictor.precision = "fp32"
    difference = np.abs(bf16.disparity - fp32.disparity)
    assert 0 < difference.mean() < 0.5, difference.mean()


@NATIVE_BF16_ONLY
def test_bf16_computes_the_convolutions_in_bf16_and_the_feature_networks_other_ops_in_fp32(first_call, tsukuba):
    predictor, *_ = first_call
    predictor.precision = "bf16"
    try:
        predictor.predict(*tsukuba, iters=ITERS)
    finally:
        predictor.precision = "fp32"
    compiled = [c for (_, _, bf16), c in predictor.openvino.compiled.items() if bf16]
    assert compiled
    for one in compiled:  # the shapes of the pair's passes
        precisions: dict[str, set[str]] = {}
        for op in one.model.get_runtime_model().get_ops():
            info = op.get_rt_info()
            precisions.setdefault(info["layerType"].astype(str), set()).add(info["runtimePrecision"].astype(str))
        assert "bf16" in precisions["Convolution"]  # (the plugin keeps a few small ones in f32)
        # the instance norms are in the feature and context networks only, before any correlation
        assert precisions["MVN"] == {"f32"}


def test_auto_picks_openvino_on_a_cpu_and_bf16_only_where_the_cpu_computes_it(tmp_path: Path, monkeypatch):
    monkeypatch.delenv("CRESTEREO_BACKEND")
    cpu = torch.device("cpu")
    assert resolve_backend("auto", cpu) == "openvino"
    assert resolve_backend("auto", torch.device("meta")) == "torch"
    monkeypatch.setenv("CRESTEREO_BACKEND", "torch")
    assert resolve_backend("auto", cpu) == "torch"
    with pytest.raises(ValueError, match="runs on the CPU"):
        resolve_backend("openvino", torch.device("meta"))
    monkeypatch.setenv("CRESTEREO_BACKEND", "tensorrt")
    with pytest.raises(ValueError, match="unknown backend"):
        resolve_backend("auto", cpu)

    flags = tmp_path / "cpuinfo"
    flags.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f\n")
    assert not native_bf16(flags)
    flags.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16\n")
    assert native_bf16(flags)
    assert not native_bf16(tmp_path / "missing")
    assert resolve_precision("auto", "torch") == "fp32"
    assert resolve_precision("bf16", "torch") == "bf16"
    assert resolve_precision("auto", "openvino") == ("bf16" if native_bf16() else "fp32")
