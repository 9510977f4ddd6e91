"""service/errors.py: the library's errors answered through one table, registered once for their
base class; the model queues' errors once for theirs. No models needed."""

from __future__ import annotations

import inspect

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

import ds3d.errors
from ds3d.errors import DataFormatError, Ds3dError, ImageTooLarge, InvalidBox, InvalidImage
from service.errors import LIBRARY_ERRORS, install_handlers, library_answer, to_api_error
from service.microbatch import ItemFailed, QueueError

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
