"""`openapi.yaml` is the contract: it equals the app's generated schema and documents every
answer `/disparity` can give."""

from __future__ import annotations

import json

import yaml

from crestereo_pp.service.openapi import openapi_schema, render_yaml
from service_helpers import REPO


def test_openapi_yaml_equals_the_generated_schema():
    committed = yaml.safe_load((REPO / "openapi.yaml").read_text())
    generated = json.loads(json.dumps(openapi_schema()))
    assert committed == generated, "regenerate: python -m crestereo_pp.service.openapi > openapi.yaml"
    assert yaml.safe_load(render_yaml(generated)) == generated


def test_every_disparity_answer_is_documented_with_examples_of_its_error_codes():
    operation = openapi_schema()["paths"]["/disparity"]["post"]
    responses = operation["responses"]
    assert set(responses) == {"200", "400", "401", "408", "413", "414", "415", "422", "500", "503"}
    assert set(responses["200"]["content"]) == {
        "application/json",
        "application/x-npz",
        "image/png",
        "application/x-ply",
    }
    for status, response in responses.items():
        assert response["description"]
        assert "X-Request-Id" in response["headers"]
        if status != "200":
            media = response["content"]["application/json"]
            assert media["schema"] == {"$ref": "#/components/schemas/ErrorResponse"}
            for code, example in media["examples"].items():
                assert example["value"]["error"]["code"] == code
    assert "Retry-After" in responses["503"]["headers"]
    assert {"queue_full", "deadline_exceeded", "loading", "draining"} <= set(
        responses["503"]["content"]["application/json"]["examples"]
    )
    assert operation["requestBody"]["content"]["multipart/form-data"]["schema"]["required"] == ["left", "right"]
    names = {parameter["name"] for parameter in operation["parameters"]}
    assert names == {
        "model",
        "format",
        "two_pass",
        "iters",
        "scale",
        "raw_uncertainty",
        "flip",
        "blend_sgbm",
        "refine_edges",
        "align_rows",
        "color_min",
        "color_max",
        "cx_px",
        "cy_px",
        "max_uncertainty",
        "focal_px",
        "baseline_m",
        "min_disparity",
        "max_depth_m",
        "frame",
        "X-Request-Timeout-Ms",
    }


def test_health_and_metrics_document_their_answers():
    paths = openapi_schema()["paths"]
    for path in ("/health", "/health/live", "/health/ready"):
        assert set(paths[path]["get"]["responses"]) == {"200", "503"}
    assert "text/plain" in paths["/metrics"]["get"]["responses"]["200"]["content"]
