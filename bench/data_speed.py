"""Throughput of the procedural stereo generator (stereo_data.synthetic), as a Markdown table.

    .venv/bin/python bench/data_speed.py                      # CPU, default batch sizes
    .venv/bin/python bench/data_speed.py --device cuda --batch-sizes 8 24 64
    .venv/bin/python bench/data_speed.py --threads 1 --batch-sizes 2 --supersample 1 2   # anti-aliasing's cost

Each cell: pairs per second of ``SceneGenerator.generate`` (scene drawing, both views, occlusion
mask, photometric changes), the median of ``--repeats`` timed calls after one warm-up call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from crestereo_pp.stereo_data.synthetic import SceneConfig, SceneGenerator

SIZES = ((128, 320), (256, 512), (384, 512))  # the CPU campaign's crops first


def pairs_per_second(generator: SceneGenerator, batch_size: int, repeats: int) -> float:
    def synchronise() -> None:
        if generator.device.type == "cuda":
            torch.cuda.synchronize(generator.device)

    generator.generate(batch_size, seed=0)  # warm-up
    seconds = []
    for seed in range(1, repeats + 1):
        synchronise()
        start = time.perf_counter()
        generator.generate(batch_size, seed=seed)
        synchronise()
        seconds.append(time.perf_counter() - start)
    return batch_size / statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's)")
    parser.add_argument(
        "--supersample", type=int, nargs="+", default=[1], help="anti-aliasing factors to compare, a row each [1]"
    )
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)

    device = torch.device(args.device)
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        name = f"CPU, {torch.get_num_threads()} threads"
    print(f"stereo_data.synthetic throughput, pairs/s ({name}, torch {torch.__version__})\n")
    print("| H x W | supersample | " + " | ".join(f"batch {b}" for b in args.batch_sizes) + " |")
    print("|---|---:|" + "---:|" * len(args.batch_sizes))
    for height, width in SIZES:
        for supersample in args.supersample:
            config = SceneConfig(height=height, width=width, supersample=supersample)
            generator = SceneGenerator(config, device=device)
            cells = [f"{pairs_per_second(generator, b, args.repeats):.1f}" for b in args.batch_sizes]
            print(f"| {height} x {width} | {supersample} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
