"""`crestereo-pp serve`: the HTTP service on this machine, or as a Ray Serve application (--ray)."""

from __future__ import annotations

import argparse
import os


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Serve the HTTP API and the web page. Plain: one process on this machine "
        "(as `python -m crestereo_pp.service`). "
        "With --ray: the same app in replicas on a Ray cluster, behind Ray's HTTP proxy (needs the `ray` extra); "
        "each answer names its replica in X-Replica. Without --address a local cluster is started and "
        "stopped again on SIGTERM or SIGINT."
    )
    parser.add_argument("--host", default=os.environ.get("UVICORN_HOST", "127.0.0.1"), help="[127.0.0.1]")
    parser.add_argument("--port", type=int, default=int(os.environ.get("UVICORN_PORT", "8000")), help="[8000]")
    ray = parser.add_argument_group("Ray Serve")
    ray.add_argument("--ray", action="store_true", help="serve as a Ray Serve application")
    ray.add_argument(
        "--address", help="an existing Ray cluster (`auto`, or the head's host:port) [a local one, started here]"
    )
    ray.add_argument("--replicas", type=int, help="a fixed number of replicas [1]")
    ray.add_argument("--min-replicas", type=int, help="autoscaling on ongoing requests: at least this many")
    ray.add_argument("--max-replicas", type=int, help="autoscaling: at most this many")
    ray.add_argument(
        "--replica-cpus",
        type=int,
        metavar="N",
        help="CPUs reserved per replica, which are its threads [the cluster's CPUs over the most replicas]",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    ray_only = {
        "--address": args.address,
        "--replicas": args.replicas,
        "--min-replicas": args.min_replicas,
        "--max-replicas": args.max_replicas,
        "--replica-cpus": args.replica_cpus,
    }
    if not args.ray:
        given = [flag for flag, value in ray_only.items() if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)} only apply with --ray")
        from crestereo_pp.service.__main__ import serve

        serve(args.host, args.port)
        return 0
    from crestereo_pp.service.ray.serve import Scale, serve_on_ray

    scale = Scale(args.replicas, args.min_replicas, args.max_replicas, args.replica_cpus)
    serve_on_ray(args.host, args.port, scale, args.address)
    return 0
