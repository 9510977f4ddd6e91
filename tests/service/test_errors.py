"""ds3d_service/errors.py: the library's errors answered through one table, registered once for
their base class; the model queues' errors once for theirs. No models needed."""

from __future__ import annotations

import inspect

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

import ds3d.errors
from ds3d.errors import DataFormatError, Ds3dError, ImageTooLarge, InvalidBox, InvalidImage
from ds3d_service.errors import LIBRARY_ERRORS, install_handlers, library_answer, to_api_error
from ds3d_service.microbatch import ItemFailed, QueueError

LIBRARY_ERROR_TYPES = [
    kind
    for _, kind in inspect.getmembers(ds3d.errors, inspect.isclass)
    if issubclass(kind, Ds3dError)
]


@pytest.mark.parametrize("kind", LIBRARY_ERROR_TYPES, ids=lambda kind: kind.__name__)
def test_every_library_error_has_its_row(kind):
    assert kind in LIBRARY_ERRORS


def test_a_subclass_not_listed_is_answered_as_its_nearest_base():
    class Smaller(ImageTooLarge):
        pass

    assert library_answer(Smaller) == library_answer(ImageTooLarge) == (422, "invalid_image")


@pytest.mark.parametrize(
    ("error", "status", "code", "message"),
    [
        (InvalidBox("bbox has no area"), 422, "invalid_box", "bbox has no area"),
        (ImageTooLarge("too many pixels"), 422, "invalid_image", "too many pixels"),
        (DataFormatError("no models"), 500, "internal", "internal error: DataFormatError"),
        (ItemFailed(2, InvalidImage("empty")), 422, "invalid_image", "items[2]: empty"),
    ],
)
def test_answers(error, status, code, message):
    answer = to_api_error(error, retry_after_s=1)
    assert (answer.status, answer.code, answer.message) == (status, code, message)


def test_each_base_is_registered_once_and_answers_in_the_route():
    app = FastAPI()
    install_handlers(app, retry_after_s=1)
    assert {Ds3dError, QueueError} <= set(app.exception_handlers)
    assert not {InvalidBox, InvalidImage, ItemFailed} & set(app.exception_handlers)

    @app.get("/box")
    async def box():
        raise InvalidBox("bbox lies outside the image")

    response = TestClient(app).get("/box")
    assert response.status_code == 422
    assert response.json() == {
        "error": {"code": "invalid_box", "message": "bbox lies outside the image"}
    }


def test_a_bug_in_a_route_is_a_json_500_counted_under_its_route():
    """The app's own middlewares (ds3d_service.app): the answer is JSON, and the request is counted
    under the route's template."""
    from ds3d_service.app import create_app
    from ds3d_service.settings import Settings

    app = create_app(Settings())

    @app.get("/v1/broken/{part}")
    async def broken(part: str):
        raise RuntimeError("a bug")

    response = TestClient(app, raise_server_exceptions=False).get("/v1/broken/x")
    assert response.status_code == 500 and response.json()["error"]["code"] == "internal"
    text = app.state.metrics.render().decode()
    assert 'ds3d_requests_total{route="/v1/broken/{part}",status="500"} 1.0' in text
