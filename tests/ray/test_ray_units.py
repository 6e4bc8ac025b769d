"""The Ray pieces that need no cluster: replica counts and CPU shares, the proxy's answers for a
lost replica, and the flags that only apply with --ray."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from ray_helpers import write_pairs
from starlette.types import Message, Receive, Scope, Send

from crestereo_pp.cli.main import main
from crestereo_pp.service.ray.cluster import cpu_share, cpu_threads
from crestereo_pp.service.ray.proxy import ProxyAnswerMiddleware
from crestereo_pp.service.ray.serve import Scale


def test_a_fixed_count_or_an_autoscaling_range_of_replicas_and_each_ones_cpus():
    assert Scale().most_replicas == 1 and not Scale().autoscaled
    assert Scale(replicas=3).most_replicas == 3
    autoscaled = Scale(min_replicas=1, max_replicas=4)
    assert autoscaled.autoscaled and autoscaled.most_replicas == 4
    assert Scale(replicas=2, cpus=3).cpus_per_replica() == 3


def test_workers_or_replicas_share_the_cpus_equally_in_fractions_of_one_where_they_outnumber_them():
    assert cpu_share(2, [8.0]) == 4.0
    assert cpu_share(3, [4.0]) == 1.3333  # Ray's steps of 1/10000, rounded down: all three fit
    assert cpu_share(4, [2.0]) == 0.5
    assert cpu_share(3, [2.0]) == 0.6666
    assert [cpu_threads(share) for share in (4.0, 1.3333, 0.5)] == [4, 1, 1]


def test_a_share_is_never_split_between_nodes_so_all_of_them_fit():
    assert cpu_share(3, [8.0, 8.0]) == 4.0  # not 16 / 3: one node holds only one share of 5.33
    assert cpu_share(3, [1.0, 1.0]) == 0.5
    assert cpu_share(2, [3.0, 1.0]) == 1.5  # both on the larger node


def test_a_cluster_without_cpus_yet_is_asked_for_one_cpu_per_worker_for_its_autoscaler_to_add():
    assert cpu_share(2, []) == 1.0
    assert cpu_share(2, [0.0]) == 1.0


@pytest.mark.parametrize(
    ("scale", "message"),
    [
        (dict(replicas=2, min_replicas=1, max_replicas=3), "not both"),
        (dict(min_replicas=1), "both --min-replicas and --max-replicas"),
        (dict(min_replicas=3, max_replicas=2), "<= --max-replicas"),
        (dict(replicas=0), "at least 1"),
        (dict(cpus=0), "--replica-cpus"),
    ],
)
def test_inconsistent_replica_counts_are_refused_saying_which_flags(scale, message):
    with pytest.raises(ValueError, match=message):
        Scale(**scale)


async def through_proxy(*messages: Message) -> list[Message]:
    """What the client gets when the replica behind Ray's proxy sends `messages` (then returns)."""
    sent: list[Message] = []

    async def replica(scope: Scope, receive: Receive, send: Send) -> None:
        for message in messages:
            await send(message)

    async def receive() -> Message:
        return {"type": "http.request", "body": b""}

    async def send(message: Message) -> None:
        sent.append(message)

    await ProxyAnswerMiddleware(replica)({"type": "http", "path": "/disparity"}, receive, send)
    return sent


@pytest.mark.anyio
@pytest.mark.parametrize(
    "lost",
    [
        (),  # the replica died before anything was sent: Ray's proxy sends nothing
        ({"type": "http.response.start", "status": 500, "headers": []}, {"type": "http.response.body", "body": b""}),
    ],
)
async def test_a_request_whose_replica_died_is_answered_503_replica_lost_with_retry_after(lost):
    start, body = await through_proxy(*lost)
    assert start["status"] == 503
    assert (b"retry-after", b"1") in start["headers"]
    assert json.loads(body["body"])["error"]["code"] == "replica_lost"


@pytest.mark.anyio
async def test_the_services_own_answers_pass_the_proxy_unchanged_but_for_repeated_headers():
    error = b'{"error": {"code": "internal_error", "message": "x"}}'
    start = {
        "type": "http.response.start",
        "status": 500,
        "headers": [(b"x-request-id", b"1"), (b"x-request-id", b"1")],
    }
    sent = await through_proxy(start, {"type": "http.response.body", "body": error})
    assert [message["type"] for message in sent] == ["http.response.start", "http.response.body"]
    assert sent[0]["status"] == 500 and sent[0]["headers"] == [(b"x-request-id", b"1")]
    assert sent[1]["body"] == error
    ok = await through_proxy(
        {"type": "http.response.start", "status": 200, "headers": []},
        {"type": "http.response.body", "body": b"{}", "more_body": False},
    )
    assert ok[0]["status"] == 200 and ok[1]["body"] == b"{}"


def test_ray_flags_without_ray_are_refused(tmp_path: Path, capsys):
    assert main(["serve", "--replicas", "2"]) == 2
    assert "--replicas only apply with --ray" in capsys.readouterr().err
    lefts, rights = write_pairs(tmp_path, 1)
    assert main(["predict", str(lefts), str(rights), "-o", str(tmp_path / "out"), "--mkdir", "--workers", "2"]) == 2
    assert "--address and --workers only apply with --ray" in capsys.readouterr().err


def test_ray_jobs_refuse_a_video_or_a_sequence(tmp_path: Path, capsys):
    lefts, rights = write_pairs(tmp_path, 1)
    assert (
        main(["predict", str(lefts), str(rights), "-o", str(tmp_path / "out"), "--mkdir", "--sequence", "--ray"]) == 2
    )
    assert "--ray takes folders or globs of pairs" in capsys.readouterr().err


def test_the_application_builder_refuses_unknown_arguments():
    from crestereo_pp.service.ray.serve import app

    with pytest.raises(ValueError, match="unknown arguments \\['replica'\\]"):
        app({"replica": "2"})


def test_predict_on_ray_joins_its_cluster_without_importing_the_web_app():
    script = (
        "import sys\n"
        "import crestereo_pp.cli.ray_predict\n"
        "web = ('fastapi', 'starlette', 'crestereo_pp.service.api')\n"
        "loaded = [name for name in web if name in sys.modules]\n"
        "assert not loaded, loaded\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
