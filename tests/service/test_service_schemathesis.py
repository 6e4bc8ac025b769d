"""A bounded schemathesis run against `openapi.yaml` on a real uvicorn process: no 5xx, and every
answer fits the documented status codes, content types, headers and schemas."""

from __future__ import annotations

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
CHECKS = [
    not_a_server_error,
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
