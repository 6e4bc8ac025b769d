"""The two loads, each a burst of client threads (service_load.py's `concurrently`) while the
server's memory is sampled: `mixed`, clients picking jobs at random for a while, and `bodies`, many
large uploads at once."""

from __future__ import annotations

import argparse
import random
import threading
import time

import cv2
import httpx
import numpy as np
from service_load import concurrently  # bench/'s sibling script: the load benchmark's bursts

from .jobs import JOBS, PAGE, Client, Outcome, classify, transport_error
from .memory import Sample, Sampler
from .payloads import build_payloads, encode
from .report import probe_summary

BOUNDARY = "mixedloadboundary7d1f"


def run_mixed(args: argparse.Namespace) -> tuple[list[Outcome], list[Sample]]:
    """`args.clients` clients, each sending jobs picked at random by weight until `args.seconds` have passed."""
    rng = random.Random(args.seed)
    t0 = time.perf_counter()
    payloads = build_payloads(args.data, args.variants, args.calibrations, rng)
    print(
        f"payloads: {len(payloads.dev)} dev pairs, {len(payloads.variants)} variants, {len(payloads.raw)} raw pairs "
        f"({len(payloads.sizes())} distinct sizes), built in {time.perf_counter() - t0:.1f} s",
        flush=True,
    )
    outcomes: list[Outcome] = []
    lock = threading.Lock()
    sampler = Sampler(args.url, args.pid, args.sample_s, verbose=True)
    end = time.monotonic() + args.seconds
    names = list(JOBS)
    weights = [JOBS[name][0] for name in names]

    def client_loop(index: int) -> None:
        client = Client(args.url, payloads, args.seed * 1000 + index, args.timeout_s)
        try:
            while time.monotonic() < end:
                job = client.rng.choices(names, weights)[0]
                results = JOBS[job][1](client)
                with lock:
                    outcomes.extend(results)
                sampler.count(len(results))
        finally:
            client.close()

    concurrently(client_loop, args.clients, args.clients)
    return outcomes, sampler.stop()


def big_body(mib: float, rng: np.random.Generator) -> tuple[bytes, str]:
    """A multipart body of about `mib` MiB and its content type: two uncompressed 16-bit RGB noise
    PNGs, the right one 8 px narrower (a valid upload that is refused, 422 `size_mismatch`, once
    decoded)."""
    side = int((mib * PAGE / 2 / 6) ** 0.5)
    left = rng.integers(0, 65536, (side, side, 3), dtype=np.uint16)
    body = b""
    for name, image in (("left", left), ("right", left[:, :-8])):
        head = (
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="{name}"; filename="{name}.png"\r\n'
            "Content-Type: image/png\r\n\r\n"
        )
        body += head.encode() + encode(image, ".png", [cv2.IMWRITE_PNG_COMPRESSION, 0]) + b"\r\n"
    body += f"--{BOUNDARY}--\r\n".encode()
    return body, f"multipart/form-data; boundary={BOUNDARY}"


def run_bodies(args: argparse.Namespace) -> tuple[list[Outcome], list[Sample]]:
    """`args.bodies` clients at once, each sending `args.rounds` big bodies back to back; `/health/live`
    probed every 0.2 s meanwhile."""
    body, content_type = big_body(args.body_mib, np.random.default_rng(args.seed))
    print(f"body: {len(body) / PAGE:.1f} MiB, {args.bodies} clients, {args.rounds} each", flush=True)
    outcomes: list[Outcome] = []
    lock = threading.Lock()
    sampler = Sampler(args.url, args.pid, 0.2, verbose=False)

    def send(_: int) -> None:
        with httpx.Client(base_url=args.url, timeout=args.timeout_s) as http:
            for _ in range(args.rounds):
                started = time.perf_counter()
                try:
                    response = http.post("/disparity", content=body, headers={"Content-Type": content_type})
                    outcome = classify("body", response, True, time.perf_counter() - started)
                except httpx.HTTPError as error:
                    outcome = transport_error("body", error, started)
                with lock:
                    outcomes.append(outcome)
                sampler.count(1)

    concurrently(send, args.bodies, args.bodies)
    time.sleep(1.0)
    samples = sampler.stop()
    print(probe_summary(samples))
    return outcomes, samples
