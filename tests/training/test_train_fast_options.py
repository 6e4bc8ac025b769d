"""The fast-step options of TrainConfig (fused AdamW, torch.compile): their plumbing on the CPU.
Their speed is a CUDA matter (bench/gpu_check measures it)."""

import pytest
import torch

from crestereo_pp.training.config import TrainConfig
from crestereo_pp.training.data import TrainingData
from crestereo_pp.training.distributed import DistributedContext
from crestereo_pp.training.trainer import Trainer, is_on, train
from training_helpers import tiny

CPU = torch.device("cpu")
ONE_PROCESS = DistributedContext(rank=0, world_size=1, local_rank=0)


@pytest.mark.parametrize(
    ("switch", "device", "expected"),
    [("auto", "cuda", True), ("auto", "cpu", False), ("on", "cpu", True), ("off", "cuda", False)],
)
def test_auto_switches_are_on_for_cuda_only(switch, device, expected):
    assert is_on(switch, torch.device(device)) is expected


def test_defaults_keep_the_cpu_step_as_it_was():
    config = TrainConfig()
    assert (config.fused_adamw, config.compile) == ("auto", False)


@pytest.mark.parametrize(("switch", "fused"), [("auto", False), ("on", True)])
def test_the_fused_adamw_switch_reaches_the_optimiser_and_a_fused_step_runs(tmp_path, switch, fused):
    result = train(tiny(tmp_path, fused_adamw=switch, max_steps=1, train_iters=(1, 1, 1)), progress=False)
    trainer = Trainer(tiny(tmp_path / "again", fused_adamw=switch), ONE_PROCESS, CPU, None, None)
    assert bool(trainer.optimizer.defaults["fused"]) is fused
    assert result.checkpoint.is_file()


def test_compile_traces_the_training_forward_and_saves_plain_weights(tmp_path, monkeypatch):
    compiled = []
    real_compile = torch.compile

    def compile_without_inductor(model, **options):
        compiled.append(model)
        return real_compile(model, backend="aot_eager", fullgraph=True, **options)  # one graph, no C++ build

    monkeypatch.setattr(torch, "compile", compile_without_inductor)
    torch._dynamo.reset()
    result = train(tiny(tmp_path, compile=True, max_steps=2, train_iters=(1, 1, 1)), progress=False)
    torch._dynamo.reset()
    assert len(compiled) == 1 and compiled[0] is result.network
    saved = torch.load(result.checkpoint, weights_only=True)["model"]
    assert set(saved) == set(result.network.state_dict())  # no "_orig_mod." prefixes


def test_the_compile_mode_reaches_torch_compile(tmp_path, monkeypatch):
    modes = []
    real_compile = torch.compile

    def compile_recording_mode(model, mode=None, **options):
        modes.append(mode)
        return real_compile(model, backend="aot_eager", **options)  # the mode is inductor's; aot_eager has none

    monkeypatch.setattr(torch, "compile", compile_recording_mode)
    torch._dynamo.reset()
    Trainer(tiny(tmp_path, compile=True, compile_mode="reduce-overhead"), ONE_PROCESS, CPU, None, None)
    torch._dynamo.reset()
    assert modes == ["reduce-overhead"]


def test_a_channels_last_step_computes_the_contiguous_loss_and_its_weights_load_anywhere(tmp_path):
    trainers = [
        Trainer(tiny(tmp_path / name, channels_last=last, train_iters=(1, 1, 1)), ONE_PROCESS, CPU, None, None)
        for name, last in (("plain", False), ("last", True))
    ]
    convolution_weights = [p for p in trainers[1].network.parameters() if p.dim() == 4 and p.shape[1] > 1]
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in convolution_weights)
    assert not all(p.is_contiguous() for p in convolution_weights)  # really NHWC in memory
    batch = next(TrainingData(trainers[0].config, 0, CPU).batches(0))
    losses = [trainer.train_step(batch) for trainer in trainers]
    assert torch.allclose(losses[0], losses[1], rtol=1e-4, atol=1e-4)
    trainers[0].network.load_state_dict(trainers[1].network.state_dict())  # a plain network takes NHWC weights
    assert torch.allclose(trainers[0].train_step(batch), trainers[1].train_step(batch), rtol=1e-3, atol=1e-3)
