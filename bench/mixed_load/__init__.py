"""Mixed load on a running service, with its memory sampled: does RSS reach a plateau?

    python bench/mixed_load --url http://127.0.0.1:8000 --pid PID [--clients 24] [--seconds 300]
                            [--sample-s 5] [--data DIR] [--seed 0] [--json OUT.json]
    python bench/mixed_load --url ... --pid PID --scenario bodies [--bodies 48] [--rounds 1]

`--pid` is the server process (`python -m crestereo_pp.service`); this benchmark starts nothing.
Every `--sample-s` it reads the resident memory of that process and, separately, of all its
descendants (the decoder processes, an OpenVINO export) from /proc, and times `GET /health/live`,
from a process of its own (the clients' threads hold this one's GIL).

`mixed` (default): `--clients` threads send requests back to back for `--seconds`, each picking a
job at random (weights in jobs.JOBS): the real pairs of `--data` (the 16-pair dev set) at their
own sizes; crops and rescales of them (many distinct image sizes: the compiled-shape caches grow
per size) with various `iters`, `scale`, `two_pass` and `format`; a few `full` requests on small
crops; raw pairs with one of several calibrations (a 320x240 camera and synthetic pinhole
cameras of the dev pairs' sizes, so that the rectifier cache churns); short `/disparity/stream`
sessions; deliberately malformed requests (undecodable image, unusable calibration, size
mismatch, invalid option), whose 4xx are expected and counted apart; and some requests with a
short `X-Request-Timeout-Ms`. Every answer is classified: 200; `expected 4xx` (a JSON error to a
malformed job); `shed` (JSON 503 with Retry-After, a stream refused at its handshake with 503
`overloaded` and Retry-After, or closed 1013/1001); anything else is `unexpected` (the run exits
1 if there is any).

`bodies`: `--bodies` threads each send `--rounds` bodies of `--body-mib` MiB back to back, all
starting at once (two 16-bit noise PNGs of different sizes: a valid upload answered 422
`size_mismatch` once decoded, or 503 beyond the upload budget), while `/health/live` is timed every
0.2 s.

The tables give RSS at the start, every minute and at the end, and the slope over the last half
of the run (least squares, MiB/min), then the answers by job, status and error code; `--json`
writes every sample and answer. Client and server share the machine: the client pre-encodes every
payload to keep its own CPU low.

The package (run from the tree, never installed; `__main__.py` says how it finds its imports, as
gpu_check's does):

    cli        the options, the scenario, the tables and the JSON file
    scenarios  `mixed` and `bodies`: the client threads (service_load.py's `concurrently`)
    payloads   the pairs, variants, raw pairs with their calibrations and stream frames, encoded
    jobs       a client's jobs and the classification of every answer
    memory     the sampling process: RSS from /proc and `/health/live`
    report     the memory table and the answers table
"""
