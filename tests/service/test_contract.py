"""The OpenAPI document is the contract clients generate from: Schemathesis generates requests
from it, schema-valid and schema-invalid, sends them to a real server and checks every answer
against the same document with all of its checks (no 5xx; status codes, content types, bodies
and headers as documented; schema-valid requests accepted, invalid ones refused)."""

from __future__ import annotations

import pytest

from tests.needs import import_or_missing

schemathesis = import_or_missing(
    "schemathesis", "schemathesis is in the dev extra: pip install -e '.[dev]'"
)
import io  # noqa: E402

from hypothesis import HealthCheck, given, settings  # noqa: E402  (comes with schemathesis)
from hypothesis import strategies as st  # noqa: E402
from PIL import Image  # noqa: E402
from schemathesis.config import SchemathesisConfig  # noqa: E402

from ds3d.inputs import MAX_ASPECT_RATIO  # noqa: E402

EXAMPLES = 25  # per operation and generation mode: bounded, about a minute in all


@st.composite
def png_images(draw) -> bytes:
    """PNG files of any size up to 96 px a side that the search takes (no longer than
    max_aspect_ratio times their width), in one colour: the images a schema's "an image" means
    (random bytes are not one, and are refused as invalid_image in the negative cases)."""
    width = draw(st.integers(1, 96))
    longest = int(width * MAX_ASPECT_RATIO)
    height = draw(st.integers(max(1, -(-width // 8)), min(96, longest)))
    colour = draw(st.tuples(*[st.integers(0, 255)] * 3))
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), colour).save(buffer, "PNG")
    return buffer.getvalue()


# /v1/pose's multipart field `image` declares image/*: generated files are real images.
schemathesis.openapi.media_type("image/png", png_images())


# A wrong request is refused with any of schemathesis's usual statuses, or with 413 when it is
# too large for the service's limits (a negative case may send hundreds of lift items), which the
# schema documents.
REFUSED = ["400", "401", "403", "404", "405", "406", "409", "413", "415", "422", "428", "429"]
CONFIG = SchemathesisConfig.from_dict(
    {"checks": {"negative_data_rejection": {"expected-statuses": REFUSED}}}
)


@pytest.fixture(scope="module")
def api(pose_engine, serving):
    with serving(pose_engine, request_timeout_s=30) as url:
        yield url, schemathesis.openapi.from_url(f"{url}/openapi.json", config=CONFIG)


def has_box(case) -> bool:
    """Whether a /v1/pose case sends a box, as a query parameter or a form field."""
    return "bbox" in (case.query or {}) or (isinstance(case.body, dict) and "bbox" in case.body)


def takes_input(operation) -> bool:
    definition = operation.definition.raw
    return bool(definition.get("parameters") or definition.get("requestBody"))


def operations(api_schema) -> list:
    return [result.ok() for result in api_schema.get_all_operations()]


@pytest.mark.parametrize("mode", list(schemathesis.GenerationMode), ids=lambda m: m.value)
def test_every_answer_keeps_the_contract(api, mode):
    url, api_schema = api
    found = operations(api_schema)
    assert {op.path for op in found} >= {"/v1/pose", "/v1/lift", "/healthz", "/readyz"}
    for operation in found:
        if mode == schemathesis.GenerationMode.NEGATIVE and not takes_input(operation):
            continue  # nothing to send wrong
        cases = operation.as_strategy(generation_mode=mode)
        if operation.path == "/v1/pose" and mode == schemathesis.GenerationMode.POSITIVE:
            # What a box needs beyond its schema (x1 > x0, y1 > y0, overlapping the image)
            # no JSON Schema can say: schema-valid boxes are refused (422 invalid_box, tested
            # in test_app.py), so the positive cases go without one.
            cases = cases.filter(lambda case: not has_box(case))

        @given(case=cases)
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
