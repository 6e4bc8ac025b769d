"""full's start from lite's weights: lite widened to full's channels (Net2Net's widening, Chen et
al. 2016), so that full's training begins where lite stands instead of from noise.

Every channel of full copies one of lite's: a convolution's weights are copied to each copy of
its output channel, and each input channel's weights are divided among that channel's copies, so
that the widened network computes what lite computes (the correlation averages over channels,
instance norm and pooling act per channel, so copies stay copies through them). Channels full has
beyond a whole multiple of lite's are new ones, zero in and out. Two differences are not carried
over exactly:
- lite's horizontal GRU gate is its super kernel, a 1x15 conv followed by a 1x5 one, where full
  has one 1x5 conv: full's is the 1x5 conv that reproduces lite's gate best, in least squares, on
  the inputs the gate meets while lite computes procedural scenes (`fitted_gate`);
- full runs two more iterations at 1/4 resolution.
Copies get identical gradients forever unless they differ: `noise` adds a little to each widened
weight, relative to its tensor's spread, so that training can pull them apart.

    python -m crestereo_pp.training.widening model/weights/lite.pt model/weights/full.pt \
        --val-data ../shared/data/stereo-dev --fp16
    crestereo-pp calibrate model/weights/full.pt
"""

from __future__ import annotations

import argparse
import datetime as dt
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from crestereo_pp.model.config import ModelConfig
from crestereo_pp.model.network import CREStereoPP
from crestereo_pp.model.update import GATE_KERNEL_CHAINS, ContextTerms, SeparableConvGRU
from crestereo_pp.model.upsample import UPSAMPLE_FACTOR
from crestereo_pp.model.weights import (
    WeightsFile,
    file_sha256,
    model_config_of,
    read_weights,
    weights_of,
    write_weights,
)

from .config import TrainConfig
from .history import RunRecord, TrainingHistory

Space = list[int | None]
"""The channels of one of full's activations: for each, the lite channel it copies (None: a new
channel, zero)."""


def copies(lite: int, full: int) -> Space:
    """`full` channels copying `lite` ones, each lite channel k times in a row (k = full // lite:
    channel j copies j // k), the rest new: the interleaving that keeps channel groups (the
    correlation's, the warp's offsets') and halves (hidden and context, z and r) together."""
    factor = full // lite
    if factor < 1:
        raise ValueError(f"cannot widen {lite} channels to {full}")
    return [j // factor if j < factor * lite else None for j in range(full)]


def joined(*parts: tuple[Space, int]) -> Space:
    """The space of a concatenation: each part's space with its lite channel count."""
    space: Space = []
    offset = 0
    for part, lite in parts:
        space += [None if source is None else offset + source for source in part]
        offset += lite
    return space


def same(channels: int) -> Space:
    """A space both networks share (the image's colours, the cost volume, the disparity)."""
    return list(range(channels))


def widened_conv(weight: Tensor, out_space: Space, in_space: Space) -> Tensor:
    """A conv weight (O, I, ...) of lite widened to (len(out_space), len(in_space), ...): each
    full output channel copies its source's weights, each input channel's divided by the number
    of its source's copies; new channels zero."""
    out_index, in_index = (torch.tensor([-1 if s is None else s for s in space]) for space in (out_space, in_space))
    counts = torch.bincount(in_index[in_index >= 0], minlength=weight.shape[1]).to(weight.dtype)
    shape = (1, -1) + (1,) * (weight.dim() - 2)
    wide = weight[out_index.clamp(min=0)][:, in_index.clamp(min=0)] / counts[in_index.clamp(min=0)].view(shape)
    wide[out_index < 0] = 0.0
    wide[:, in_index < 0] = 0.0
    return wide


def widened_bias(bias: Tensor, out_space: Space) -> Tensor:
    """A conv bias (O,) of lite widened to (len(out_space),): copied, new channels zero."""
    return torch.stack([bias[s] if s is not None else bias.new_zeros(()) for s in out_space])


GATE_FIT_SCENES = 8
"""Procedural scenes (`GATE_FIT_SIZE`, disparities to 96 px, training seeds from 0) on which
full's gate is fitted: more changed nothing (32 scenes: lite with the fitted gate at 10.23
against 10.21 % dev bad-2)."""
GATE_FIT_SIZE = (256, 512)


def horizontal_gate(lite: CREStereoPP) -> tuple[nn.Sequential, nn.Conv2d, nn.Conv2d]:
    """lite's horizontal z/r gate (the chain of convs), its first conv and its last."""
    gru = lite.update.gru
    assert isinstance(gru, SeparableConvGRU)  # lite's: a 3x3 ConvGRU has no horizontal gate
    first, last = gru.zr1[0], gru.zr1[-1]
    assert isinstance(first, nn.Conv2d) and isinstance(last, nn.Conv2d)
    return gru.zr1, first, last


def gate_inputs(lite: CREStereoPP, left: Tensor, right: Tensor) -> list[Tensor]:
    """The inputs [h, motion, context] (B, I, h, w) that lite's horizontal gate meets at every
    iteration, in order, while `lite` computes the (B, 3, H, W) pair."""
    inputs: list[Tensor] = []
    context: list[Tensor] = []
    context_terms = lite.update.context_terms

    def recording_context(stage_context: Tensor) -> ContextTerms:  # the stage's context, which the gate reads too
        context[:] = [stage_context]
        return context_terms(stage_context)

    def record(_: nn.Module, args: tuple[Tensor, ...]) -> None:
        inputs.append(torch.cat((args[0], args[1], context[0]), dim=1))

    hook = lite.update.gru.register_forward_pre_hook(record)
    setattr(lite.update, "context_terms", recording_context)  # noqa: B010 (the instance's, over the class's method)
    try:
        with torch.no_grad():
            lite.eval()(left, right)
    finally:
        hook.remove()
        del lite.update.context_terms  # the class's method again
    return inputs


def fitted_gate(
    lite: CREStereoPP, width: int, scenes: int = GATE_FIT_SCENES, size: tuple[int, int] = GATE_FIT_SIZE
) -> tuple[Tensor, Tensor]:
    """The 1x`width` conv (2H, I, 1, width) and its bias (2H,) that best reproduce lite's
    horizontal z/r gate (before the sigmoid; I = [h, motion, context]) in least squares, over the
    inputs the gate meets (`gate_inputs`) while `lite` computes `scenes` procedural scenes."""
    from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

    gate, first, last = horizontal_gate(lite)
    inputs, outputs = first.in_channels, last.out_channels
    features = inputs * width + 1  # each input channel at `width` columns, and the bias
    normal = torch.zeros(features, features, dtype=torch.float64)
    moments = torch.zeros(features, outputs, dtype=torch.float64)
    generator = SceneGenerator(SceneConfig(height=size[0], width=size[1], max_disparity=96.0 * size[1] / 512))
    for start in range(0, scenes, 4):
        batch = generator.generate(min(4, scenes - start), seed=start)
        for x in gate_inputs(lite, batch.left, batch.right):
            columns = F.unfold(x, (1, width), padding=(0, width // 2))  # (B, I * width, h * w), channel-major
            rows = torch.cat((columns, torch.ones_like(columns[:, :1])), 1).transpose(1, 2).reshape(-1, features)
            with torch.no_grad():
                target = gate(x).flatten(2).transpose(1, 2).reshape(-1, outputs)
            normal.add_(rows.T.double() @ rows.double())
            moments.add_(rows.T.double() @ target.double())
    ridge = 1e-6 * normal.diagonal().mean() * torch.eye(features, dtype=torch.float64)
    solution = torch.linalg.solve(normal + ridge, moments).float()  # (I * width + 1, 2H)
    return solution[:-1].T.reshape(outputs, inputs, 1, width).contiguous(), solution[-1].contiguous()


def parameter_spaces(lite: ModelConfig, full: ModelConfig) -> dict[str, tuple[Space, Space]]:
    """(output space, input space) of every convolution of the network, by its parameter name
    without ".weight" / ".bias"."""
    c1, c2 = lite.fem_channels, full.fem_channels
    block_in = (c1[0], c1[0], c1[0], c1[1], c1[1], c1[2])
    block_out = (c1[0], c1[0], c1[1], c1[1], c1[2], c1[2])
    width = dict(zip(c1, c2, strict=True))
    feature = copies(lite.feature_dim, full.feature_dim)
    hidden = copies(lite.hidden_dim, full.hidden_dim)
    spaces: dict[str, tuple[Space, Space]] = {"fem.stem.0": (copies(c1[0], c2[0]), same(3))}
    for index, (into, out) in enumerate(zip(block_in, block_out, strict=True)):
        into_space, out_space = copies(into, width[into]), copies(out, width[out])
        spaces[f"fem.stages.{index}.conv1"] = (out_space, into_space)
        spaces[f"fem.stages.{index}.conv2"] = (out_space, out_space)
        spaces[f"fem.stages.{index}.shortcut"] = (out_space, into_space)
    spaces["fem.head"] = (feature, copies(c1[2], c2[2]))
    spaces["ugac.warp"] = (feature, feature)
    offsets = copies(lite.offset_hidden, full.offset_hidden)
    offset_in = joined((feature, lite.feature_dim), (feature, lite.feature_dim), (same(1), 1))
    spaces["ugac.warp.offsets.layers.0"] = (offsets, offset_in)
    spaces["ugac.warp.offsets.layers.2"] = (offsets, offsets)
    spaces["ugac.warp.offsets.layers.4"] = (same(lite.offset_groups * 9), offsets)
    volume = same(lite.corr_groups * 9)
    corr1, corr2 = (copies(a, b) for a, b in zip(lite.corr_hidden, full.corr_hidden, strict=True))
    disp1, disp2 = (copies(a, b) for a, b in zip(lite.disp_hidden, full.disp_hidden, strict=True))
    fused = copies(lite.hidden_dim - 1, full.hidden_dim - 1)
    spaces["update.encoder.corr1"] = (corr1, volume)
    spaces["update.encoder.corr2"] = (corr2, corr1)
    spaces["update.encoder.disp1"] = (disp1, same(1))
    spaces["update.encoder.disp2"] = (disp2, disp1)
    spaces["update.encoder.fuse"] = (
        fused,
        joined((corr2, lite.corr_hidden[1]), (disp2, lite.disp_hidden[1])),
    )
    motion = joined((fused, lite.hidden_dim - 1), (same(1), 1))
    gate_in = joined((hidden, lite.hidden_dim), (motion, lite.hidden_dim), (hidden, lite.hidden_dim))
    gates = copies(2 * lite.hidden_dim, 2 * full.hidden_dim)  # z and r, each a hidden space
    for name in ("zr1.0", "zr2.0"):
        spaces[f"update.gru.{name}"] = (gates, gate_in)
    for name in ("q1", "q2"):
        spaces[f"update.gru.{name}"] = (hidden, gate_in)
    heads = copies(lite.head_hidden, full.head_hidden)
    for name, outputs in (("disparity_head", 1), ("mask_head", 9 * UPSAMPLE_FACTOR**2)):
        spaces[f"update.{name}.0"] = (heads, hidden)
        spaces[f"update.{name}.2"] = (same(outputs), heads)
    return spaces


def widen(lite_state: dict[str, Tensor], lite: ModelConfig, full: ModelConfig, noise: float = 0.0) -> dict[str, Tensor]:
    """full's state_dict from lite's (`widen`ed as the module says), each widened weight with
    Gaussian noise of `noise` times its tensor's standard deviation added."""
    state = {name: tensor.float() for name, tensor in lite_state.items()}
    if lite.gru_kernels != full.gru_kernels:  # lite's super kernel as full's single gate conv
        (full_width,) = GATE_KERNEL_CHAINS[full.gru_kernels]  # one conv: what a gate can be fitted to
        network = CREStereoPP(lite)
        network.load_state_dict(state)
        state["update.gru.zr1.0.weight"], state["update.gru.zr1.0.bias"] = fitted_gate(network, full_width)
    wide = {}
    for name, (out_space, in_space) in parameter_spaces(lite, full).items():
        weight = widened_conv(state[f"{name}.weight"], out_space, in_space)
        wide[f"{name}.weight"] = weight + noise * weight.std() * torch.randn_like(weight)
        wide[f"{name}.bias"] = widened_bias(state[f"{name}.bias"], out_space)
    return wide


def widened_weights(lite_path: Path, noise: float, seed: int, val_data: str | None, half: bool = False) -> WeightsFile:
    """A full weights file from the lite one at `lite_path`: its widened network, lite's training
    record with a run recording the widening (and, with `val_data`, its validation there, as a
    training run records one), lite's training config for full; with `half`, stored as float16
    (`weights_of`), and validated so."""
    from .trainer import validate

    lite_file = read_weights(lite_path)
    lite, full = model_config_of(lite_file, "lite"), ModelConfig.preset("full")
    torch.manual_seed(seed)
    network = CREStereoPP(full)
    state = widen(lite_file["model"], lite, full, noise)
    network.load_state_dict({name: t.half().float() for name, t in state.items()} if half else state)
    train_config = replace(TrainConfig.from_dict(lite_file["train_config"]), model="full", train_iters=None)
    history = TrainingHistory.from_dict(lite_file.get("training"))
    record = RunRecord(
        started=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        origin=f"widened from lite {file_sha256(lite_path)[:16]}",
        model="full",
        device="cpu",
        processes=1,
        first_step=0,
        last_step=0,
    )
    if val_data is not None:
        record.validation = validate(network, replace(train_config, val_data=val_data), torch.device("cpu"))
    history.runs.append(record)
    payload = WeightsFile(
        model=network.state_dict(),
        config=full.to_dict(),
        model_name="full",
        train_config=train_config.to_dict(),
        step=0,
        training=history.to_dict(),
    )
    return weights_of(payload, half=half)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Write full's weights widened from lite's (see the module).")
    parser.add_argument("lite", type=Path, help="lite's weights file")
    parser.add_argument("out", type=Path, help="full's weights file to write")
    parser.add_argument("--noise", type=float, default=0.01, help="noise per weight, times its tensor's std [0.01]")
    parser.add_argument("--seed", type=int, default=0, help="the noise's seed [0]")
    parser.add_argument("--val-data", help="real pairs to validate the widened network on (one pass), recorded")
    parser.add_argument("--fp16", action="store_true", help="store the weights as float16 (half the size)")
    args = parser.parse_args(argv)
    payload = widened_weights(args.lite, args.noise, args.seed, args.val_data, half=args.fp16)
    write_weights(payload, args.out)
    validation = payload["training"]["runs"][-1]["validation"]
    print(f"wrote {args.out}" + (f": {validation}" if validation else ""))


if __name__ == "__main__":
    main()
