"""The OpenAPI document is the contract clients generate from: Schemathesis generates requests
from it, schema-valid and schema-invalid, sends them to a real server and checks every answer
against the same document with all of its checks (no 5xx; status codes, content types, bodies
and headers as documented; schema-valid requests accepted, invalid ones refused). Configured as
`st run` is, by the repository's schemathesis.toml (its image strategy, its refusal statuses)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from tests.needs import import_or_missing

schemathesis = import_or_missing(
    "schemathesis", "schemathesis is in the dev extra: pip install -e '.[dev]'"
)
from hypothesis import HealthCheck, given, settings  # noqa: E402  (comes with schemathesis)
from schemathesis.config import SchemathesisConfig  # noqa: E402

import tests.service.schemathesis_hooks  # noqa: E402, F401  (registers what an image is)

EXAMPLES = 25  # per operation and generation mode: bounded, about a minute in all
# The CLI's configuration, its hooks imported above (the file names them relative to the
# repository root, where `st run` is started; pytest may start elsewhere).
TOML = Path(__file__).resolve().parents[2] / "schemathesis.toml"
CONFIG = SchemathesisConfig.from_dict(
    {k: v for k, v in tomllib.loads(TOML.read_text()).items() if k != "hooks"}
)


@pytest.fixture(scope="module")
def api(pose_engine, serving):
    with serving(pose_engine, request_timeout_s=30) as url:
        yield url, schemathesis.openapi.from_url(f"{url}/openapi.json", config=CONFIG)


def takes_input(operation) -> bool:
    definition = operation.definition.raw
    return bool(definition.get("parameters") or definition.get("requestBody"))


def operations(api_schema) -> list:
    return [result.ok() for result in api_schema.get_all_operations()]


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(schemathesis.GenerationMode), ids=lambda m: m.value)
def test_every_answer_keeps_the_contract(api, mode):
    url, api_schema = api
    found = operations(api_schema)
    assert {op.path for op in found} >= {"/v1/pose", "/v1/lift", "/healthz", "/readyz"}
    for operation in found:
        if mode == schemathesis.GenerationMode.NEGATIVE and not takes_input(operation):
            continue  # nothing to send wrong

        @given(case=operation.as_strategy(generation_mode=mode))
        @settings(
            max_examples=EXAMPLES,
            deadline=None,
            derandomize=True,  # the same cases on every run: a red run reproduces
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        def keeps_the_contract(case):
            case.call_and_validate(base_url=url)

        keeps_the_contract()


def test_the_pose_box_is_in_the_document_and_the_corner_form_is_not(api):
    """/v1/pose documents `box`, whose schema holds all its rules; the corner form `bbox` that
    earlier clients send is read but not documented, since no schema can say its rules."""
    _, api_schema = api
    (pose,) = [op for op in operations(api_schema) if op.path == "/v1/pose"]
    query = {p["name"] for p in pose.definition.raw["parameters"] if p["in"] == "query"}
    form = pose.definition.raw["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert {"box", "intrinsics"} <= query and "bbox" not in query
    assert set(form["properties"]) == {"image", "box", "intrinsics"}
    assert form["additionalProperties"] is False
