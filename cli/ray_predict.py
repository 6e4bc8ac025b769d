"""`crestereo-pp predict --ray`: folders or globs of pairs as a Ray job.

A pool of workers (Ray actors), each loading the model once and writing its pairs' outputs itself
(on a cluster of several machines, the inputs and the output folders are paths every machine
sees: a shared file system). Pairs whose outputs all exist are skipped, so a re-run finishes an
interrupted job; a pair that fails is reported with its reason and the others go on.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from typing import Any

from tqdm import tqdm

from crestereo_pp.service.batching.cpu import configure_torch_threads
from crestereo_pp.service.ray.cluster import connect, cpu_share, cpu_threads, node_cpus, require_ray, reserve_cpus

from .options import load_predictor
from .prediction import (
    OFF_ROWS_PX,
    Job,
    PairImages,
    PairPaths,
    describe_off_rows,
    frame_options,
    is_complete,
    plan,
    predict_and_write,
    read_pair,
)

SHOWN_FAILURES = 20


@dataclass(frozen=True)
class PairResult:
    """How one pair went: `error` is None when its outputs were written; `rows_off_px` the largest
    offset of its right rows from the left's, where measured (`predict_and_write`)."""

    pair: PairPaths
    error: str | None
    rows_off_px: float | None = None


class PairWorker:
    """One worker of the pool: the command's job and a loaded model (a Ray actor's body)."""

    def __init__(self, args: argparse.Namespace, threads: int) -> None:
        configure_torch_threads(threads)
        self.job = plan(args)
        self.stream = load_predictor(args).stream(frame_options(args), None)

    def ready(self) -> None:
        """Returns once the worker has its model (an error where it could not load it)."""

    def compute(self, pair: PairPaths) -> PairResult:
        try:
            offset = predict_and_write(self.job, self.stream, PairImages(pair, *read_pair(pair)))
        except Exception as error:  # reported per pair; the job goes on
            return PairResult(pair, f"{type(error).__name__}: {error}")
        return PairResult(pair, None, None if offset is None else offset.largest_px)


def run_on_ray(job: Job) -> int:
    """Run the job's pairs on a Ray cluster; exit status 1 where any pair failed."""
    require_ray()
    import ray
    from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

    args = job.args
    pairs = job.pairs
    if args.sequence or pairs is None:
        raise ValueError("--ray takes folders or globs of pairs; a sequence or a video is one camera's ordered frames")
    if args.workers is not None and args.workers < 1:
        raise ValueError("--workers must be at least 1")
    todo = [pair for pair in pairs if not is_complete(job, pair)]
    if len(todo) < len(pairs):
        print(f"skipping {len(pairs) - len(todo)} pair(s) whose outputs all exist (delete them to compute again)")
    if not todo:
        print(f"nothing to compute: all {len(pairs)} pair(s) are done")
        return 0
    connect(args.address)
    try:
        nodes = node_cpus()
        workers = min(args.workers if args.workers is not None else max(1, int(sum(nodes))), len(todo))
        cpus = cpu_share(workers, nodes)
        started = time.perf_counter()
        placement = PlacementGroupSchedulingStrategy(reserve_cpus(workers, cpus))
        actor = ray.remote(num_cpus=cpus, max_restarts=1, max_task_retries=1, scheduling_strategy=placement)(PairWorker)
        pool: list[Any] = [actor.remote(args, cpu_threads(cpus)) for _ in range(workers)]
        try:
            ray.get([worker.ready.remote() for worker in pool])
        except ray.exceptions.RayActorError as error:
            raise ValueError(f"the workers could not start: {error}") from None
        print(f"{workers} worker(s) of {cpus:g} CPU(s) ready in {time.perf_counter() - started:.1f} s")
        try:
            results = _run_pool(pool, todo, args.model)
        except KeyboardInterrupt:
            done = sum(is_complete(job, pair) for pair in pairs)
            print(f"interrupted: {done} of {len(pairs)} pair(s) done; the same command again computes the rest")
            return 130
    finally:
        ray.shutdown()
    return _report(results, len(pairs) - len(todo))


def _run_pool(pool: list[Any], todo: list[PairPaths], model: str) -> tuple[list[PairResult], float]:
    """Each worker computes one pair at a time, the next as soon as it is free; a worker that dies
    for good fails its pair, and the others take the rest."""
    import ray

    started = time.perf_counter()
    waiting = list(reversed(todo))
    running: dict[Any, tuple[Any, PairPaths]] = {}
    results: list[PairResult] = []

    def give(worker: Any) -> None:
        if waiting:
            pair = waiting.pop()
            running[worker.compute.remote(pair)] = (worker, pair)

    for worker in pool:
        give(worker)
    with tqdm(total=len(todo), desc=f"predict {model} (ray)", unit="pair") as progress:
        while running:
            [done], _ = ray.wait(list(running), num_returns=1)
            worker, pair = running.pop(done)
            try:
                results.append(ray.get(done))
            except ray.exceptions.RayActorError as error:
                results.append(PairResult(pair, f"its worker died: {error.__class__.__name__}"))
            else:
                give(worker)
            progress.update(1)
    # Left over only where every worker died.
    results += [PairResult(pair, "no worker left to compute it") for pair in reversed(waiting)]
    return results, time.perf_counter() - started


def _report(run: tuple[list[PairResult], float], skipped: int) -> int:
    results, seconds = run
    failed = [result for result in results if result.error is not None]
    computed = len(results) - len(failed)
    print(
        f"computed {computed} pair(s) in {seconds:.1f} s ({computed / seconds:.2f} pairs/s); "
        f"skipped {skipped} already done; failed {len(failed)}"
    )
    for result in failed[:SHOWN_FAILURES]:
        print(f"failed {result.pair.left} {result.pair.right}: {result.error}")
    if len(failed) > SHOWN_FAILURES:
        print(f"... and {len(failed) - SHOWN_FAILURES} more")
    off_rows = [px for px in (result.rows_off_px for result in results) if px is not None and px >= OFF_ROWS_PX]
    if off_rows:
        print(describe_off_rows(off_rows, computed))
    return 1 if failed else 0
