"""A bounded schemathesis run against `openapi.yaml` on a real uvicorn process: no 5xx, and every
answer fits the documented status codes, content types, headers and schemas."""

from __future__ import annotations

from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from service_helpers import REPO, encode, stereo_pair

schema = schemathesis.openapi.from_path(REPO / "openapi.yaml")


@schemathesis.check
def not_a_server_error_unless_asked_for(ctx: Any, response: Any, case: Any) -> bool | None:
    """No 5xx, except the answer a request asked for itself: 503 `deadline_exceeded` when it set
    `X-Request-Timeout-Ms` (a generated deadline of 1 ms passes while its images are read)."""
    if (
        response.status_code == 503
        and "X-Request-Timeout-Ms" in (case.headers or {})
        and response.json()["error"]["code"] == "deadline_exceeded"
    ):
        return True
    return not_a_server_error(ctx, response, case)


CHECKS = [
    not_a_server_error_unless_asked_for,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]


@schema.parametrize()
@settings(max_examples=25, deadline=None, database=None, suppress_health_check=list(HealthCheck))
def test_the_service_honours_its_openapi_contract(case, default_server):
    case.call_and_validate(base_url=default_server.base_url, checks=CHECKS, timeout=60)


@pytest.mark.parametrize("format", ["json", "npz", "png", "disparity_png16"])
def test_successful_answers_fit_the_contract(format, default_server):
    left, right = stereo_pair()
    case = schema["/disparity"]["POST"].Case(
        body={"left": encode(left), "right": encode(right)}, query={"format": format}, media_type="multipart/form-data"
    )
    response = case.call_and_validate(base_url=default_server.base_url, checks=CHECKS, timeout=60)
    assert response.status_code == 200


def test_a_deadline_the_request_set_itself_is_a_documented_answer_not_a_server_error(default_server):
    left, right = stereo_pair()
    case = schema["/disparity"]["POST"].Case(
        body={"left": encode(left), "right": encode(right)},
        headers={"X-Request-Timeout-Ms": "1"},
        media_type="multipart/form-data",
    )
    response = case.call_and_validate(base_url=default_server.base_url, checks=CHECKS, timeout=60)
    assert response.status_code == 503 and response.json()["error"]["code"] == "deadline_exceeded"
