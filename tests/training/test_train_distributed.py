"""Two-process DistributedDataParallel training on the CPU (gloo), as torchrun would start it."""

import os
from pathlib import Path

import torch
import torch.multiprocessing as mp

from crestereo_pp.model import CREStereoPP, ModelConfig
from crestereo_pp.service.local import free_port
from crestereo_pp.training.records import read_csv
from crestereo_pp.training.trainer import train
from training_helpers import tiny

WORLD_SIZE = 2


def train_as_rank(rank: int, port: int, out_dir: str) -> None:
    """What torchrun does for each process: set the rendezvous variables, then run the command."""
    os.environ.update(
        RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(WORLD_SIZE), MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port)
    )
    torch.set_num_threads(1)
    # a flat-decay run within a time budget: the ranks agree on whether its steps left fit the time
    config = tiny(Path(out_dir), max_steps=4, schedule="flat-decay", decay_steps=1, max_minutes=60.0)
    result = train(config, progress=False)
    torch.save(result.network.state_dict(), Path(out_dir) / f"rank{rank}.pt")


def test_two_ranks_complete_and_end_with_identical_trained_weights(tmp_path):
    mp.spawn(train_as_rank, args=(free_port(), str(tmp_path)), nprocs=WORLD_SIZE, join=True)

    rank0 = torch.load(tmp_path / "rank0.pt")
    rank1 = torch.load(tmp_path / "rank1.pt")
    assert all(torch.equal(rank0[name], rank1[name]) for name in rank0)
    torch.manual_seed(0)  # the config's seed: the weights both ranks started from
    initial = CREStereoPP(ModelConfig.preset("lite")).state_dict()
    assert not all(torch.equal(rank0[name], initial[name]) for name in rank0)
    rows = read_csv(tmp_path / "log.csv")  # written by rank 0 only, counting both ranks' pairs
    assert [int(r["pairs_seen"]) for r in rows] == [2, 4, 6, 8]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "checkpoint.pt",
        "log.csv",
        "loss_curve.png",
        "rank0.pt",
        "rank1.pt",
        "stable.pt",
    ]
