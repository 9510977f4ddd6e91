"""GET /v1/skeleton (ds3d_service/routes/skeleton.py): the library's own skeleton (ds3d.skeleton,
the colours of ds3d.viz.overlay), declared in the OpenAPI, open without a key; and the web page
draws with it instead of a copy of its own."""

from __future__ import annotations

import asyncio
import re

import httpx
import pytest

from ds3d import skeleton
from ds3d.viz import overlay
from ds3d_service.app import create_app
from ds3d_service.routes.page import STATIC_DIR
from ds3d_service.settings import Settings

KEY = "skeleton-test-key-0123456789"


def get(app, path: str, **kwargs) -> httpx.Response:
    """A GET straight to the app (httpx's ASGI transport; no models, no lifespan)."""

    async def send() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://skeleton.test") as c:
            return await c.get(path, **kwargs)

    return asyncio.run(send())


@pytest.fixture(scope="module")
def app():
    """An app with API keys: the skeleton must not need one."""
    return create_app(Settings(api_keys=KEY))


def test_the_skeleton_is_the_librarys(app):
    resp = get(app, "/v1/skeleton")
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["joint_names"] == list(skeleton.JOINT_NAMES)
    assert body["parents"] == list(skeleton.PARENT)
    assert body["limbs"] == [list(limb) for limb in skeleton.LIMBS]
    assert body["bone_names"] == list(skeleton.BONE_NAMES)
    assert body["joint_sets"] == {
        name: {"description": skeleton.SET_DESCRIPTIONS[name], "joints": list(joints)}
        for name, joints in skeleton.JOINT_SETS.items()
    }
    # each joint's colour as ds3d draws its limb (ds3d.viz.overlay, ds3d.viz.render)
    colours = [tuple(body["colours"][side]) for side in body["sides"]]
    assert colours == [overlay.limb_colour(j) for j in range(skeleton.NUM_JOINTS)]
    assert body["sides"][skeleton.NECK] == body["sides"][skeleton.HEAD_TOP] == "centre"
    assert body["sides"][skeleton.R_HIP] == "right" and body["sides"][skeleton.L_HIP] == "left"


def test_the_openapi_declares_it_open(app):
    schema = get(app, "/openapi.json").json()
    operation = schema["paths"]["/v1/skeleton"]["get"]
    answer = operation["responses"]["200"]["content"]["application/json"]["schema"]
    assert answer == {"$ref": "#/components/schemas/Skeleton"}
    declared = schema["components"]["schemas"]["Skeleton"]["properties"]
    assert set(declared) == set(get(app, "/v1/skeleton").json())
    assert "security" not in operation  # /v1/pose and /v1/lift declare the key schemes
    assert "security" in schema["paths"]["/v1/lift"]["post"]


def test_the_page_keeps_no_copy_of_the_skeleton():
    script = (STATIC_DIR / "app.js").read_text()
    assert '"v1/skeleton"' in script
    # the hips are looked up by name (the 3D view stands people on their midpoint); no other
    # joint is named, and no joint set is described
    named = {name for name in skeleton.JOINT_NAMES if re.search(rf"\b{name}\b", script)}
    assert named == {"right_hip", "left_hip"}
    for description in skeleton.SET_DESCRIPTIONS.values():
        assert description not in script
    style = (STATIC_DIR / "style.css").read_text()
    for rgb in overlay.SIDE_COLOURS.values():
        pattern = r"rgb\(\s*{}\s*,\s*{}\s*,\s*{}\s*\)".format(*rgb)
        assert not re.search(pattern, script + style), rgb
