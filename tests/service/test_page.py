"""The web page at / (ds3d_service/routes/page.py, ds3d_service/static/): served with a strict
security policy and nothing from elsewhere; and, in a real browser (Debian's chromium driven by
playwright), the round trip a user makes: a photo in (file, drop, paste, webcam), the skeleton
drawn over it and in a 3D view that turns and zooms, the API's own error messages, an API key,
and a phone-sized screen.

DS3D_PAGE_SCREENSHOT=docs/page.png writes the screenshot of the README while the test runs.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import re
import shutil
from pathlib import Path

import httpx
import pytest

from ds3d_service.app import create_app
from ds3d_service.routes.page import PAGE_CSP, STATIC_DIR
from ds3d_service.settings import Settings
from tests.needs import missing

KEY = "page-test-key-0123456789"
CHROMIUM_ENV = "DS3D_CHROMIUM"
SCREENSHOT_ENV = "DS3D_PAGE_SCREENSHOT"
# The browser's fake webcam (a moving test pattern), allowed without asking.
CHROMIUM_ARGS = ["--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream"]

# ------------------------------------------------------------------------------------------------
# Served as it should be (no browser, no models: the app runs without its lifespan).


class Client:
    """Requests straight to the app (httpx's ASGI transport, without the app's lifespan)."""

    def __init__(self, app):
        self.app = app

    def request(self, method: str, path: str, **kwargs) -> httpx.Response:
        async def send() -> httpx.Response:
            transport = httpx.ASGITransport(app=self.app)
            async with httpx.AsyncClient(transport=transport, base_url="http://page.test") as c:
                return await c.request(method, path, **kwargs)

        return asyncio.run(send())

    def get(self, path: str, **kwargs) -> httpx.Response:
        return self.request("GET", path, **kwargs)

    def head(self, path: str, **kwargs) -> httpx.Response:
        return self.request("HEAD", path, **kwargs)


@pytest.fixture(scope="module")
def client():
    """An app with API keys, which the page and its files must not need."""
    return Client(create_app(Settings(api_keys=KEY)))


def test_the_page_has_a_strict_content_security_policy(client):
    resp = client.get("/")
    assert resp.status_code == 200
    assert resp.headers["content-type"] == "text/html; charset=utf-8"
    csp = resp.headers["content-security-policy"]
    assert csp == PAGE_CSP
    directives = dict(d.strip().split(" ", 1) for d in csp.split(";"))
    assert directives == {
        "default-src": "'self'",
        "script-src": "'self'",
        "style-src": "'self'",
        "img-src": "'self' blob: data:",
        "media-src": "'self' blob:",
        "connect-src": "'self'",
        "frame-ancestors": "'none'",
        "base-uri": "'none'",
        "form-action": "'none'",
    }
    assert resp.headers["x-frame-options"] == "DENY"
    assert resp.headers["x-content-type-options"] == "nosniff"
    assert client.head("/").status_code == 200


def test_the_static_files_are_served_with_their_media_types(client):
    page = client.get("/").text
    for name, media_type in [
        ("app.js", "text/javascript; charset=utf-8"),
        ("style.css", "text/css; charset=utf-8"),
    ]:
        assert f'"static/{name}"' in page
        resp = client.get(f"/static/{name}")
        assert resp.status_code == 200, resp.text
        assert resp.headers["content-type"] == media_type
        assert resp.content == (STATIC_DIR / name).read_bytes()
        # revalidated on each load, and not sent again while unchanged
        assert resp.headers["cache-control"] == "no-cache"
        again = client.get(f"/static/{name}", headers={"If-None-Match": resp.headers["etag"]})
        assert again.status_code == 304 and not again.content


def test_only_the_page_files_are_served(client):
    for name in ["nothing.js", "..%2Fpage.py", "..%2F..%2Fpyproject.toml", "%2Fetc%2Fpasswd"]:
        resp = client.get(f"/static/{name}")
        assert resp.status_code == 404, name
        assert resp.json()["error"]["code"] == "not_found"
    paths = client.get("/openapi.json", headers={"Authorization": f"Bearer {KEY}"}).json()["paths"]
    assert "/" not in paths and not any(p.startswith("/static") for p in paths)


def test_the_page_loads_nothing_from_elsewhere():
    """Works offline and under the policy: no URL with a host, no inline script or style."""
    for path in STATIC_DIR.iterdir():
        text = path.read_text()
        assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, re.I), path.name
    page = (STATIC_DIR / "index.html").read_text()
    assert re.findall(r"<script[^>]*>", page) == ['<script type="module" src="static/app.js">']
    assert "<style" not in page and " style=" not in page and " on" + "click=" not in page


# ------------------------------------------------------------------------------------------------
# In a real browser.


def chromium_path() -> str | None:
    """$DS3D_CHROMIUM, else a Chromium (or Chrome) on the PATH."""
    if given := os.environ.get(CHROMIUM_ENV):
        return given
    names = ("chromium", "chromium-browser", "google-chrome")
    return next((found for name in names if (found := shutil.which(name))), None)


@pytest.fixture(scope="module")
def browser():
    try:
        from playwright.sync_api import Error, sync_playwright
    except ImportError:
        missing("no playwright: pip install -e '.[dev]' (the browser: apt-get install chromium)")
    path = chromium_path()
    if path is None:
        missing(f"no chromium: apt-get install chromium, or set ${CHROMIUM_ENV} to one")
    with sync_playwright() as playwright:
        try:
            launched = playwright.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        except Error as exc:
            missing(f"chromium at {path} did not start: {exc}")
        yield launched
        launched.close()


@pytest.fixture(scope="module")
def site(engine, serving):
    with serving(engine, max_wait_ms=5) as url:
        yield url


@pytest.fixture(scope="module")
def photo(data_dir) -> Path:
    """An LSP test image: one person."""
    from ds3d.data.lsp import load_lsp

    return load_lsp(split="test").image_paths[0]


@pytest.fixture
def open_page(browser):
    """open_page(url, **context options): a new page at url, closed after the test, which fails
    on any script error on the page."""
    contexts, errors = [], []

    def open_(url: str, **options):
        context = browser.new_context(**{"viewport": {"width": 1200, "height": 800}, **options})
        contexts.append(context)
        page = context.new_page()
        page.set_default_timeout(20_000)
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url)
        return page

    yield open_
    for context in contexts:
        context.close()
    assert not errors, errors


def wait_answers(page, count: int) -> None:
    """Until the page has had `count` answers (its own counter: the policy forbids the
    evaluated strings of wait_for_function)."""
    page.wait_for_selector(f'#result[data-answers="{count}"]', state="attached")


# Non-background pixels of a canvas, and the share of them that differ from the last call's.
PIXELS_JS = """canvas => {
    const data = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
    const away = (i, j) => Math.abs(data[i] - data[j]) + Math.abs(data[i + 1] - data[j + 1])
        + Math.abs(data[i + 2] - data[j + 2]);
    let drawn = 0, changed = 0;
    const before = window.__lastFrame;
    for (let i = 0; i < data.length; i += 4) {
        if (away(i, 0) > 24) drawn++;
        if (before && before.length === data.length && Math.abs(before[i] - data[i])
            + Math.abs(before[i + 1] - data[i + 1]) + Math.abs(before[i + 2] - data[i + 2]) > 24)
            changed++;
    }
    window.__lastFrame = data;
    return {drawn: drawn / (data.length / 4), changed: changed / (data.length / 4)};
}"""


def pixels(page) -> dict[str, float]:
    return page.eval_on_selector("#view3d", PIXELS_JS)


def view3d(page) -> dict[str, float]:
    data = page.eval_on_selector("#view3d", "c => ({...c.dataset})")
    return {k: float(v) for k, v in data.items()}


def drag(page, selector: str, dx: float, dy: float, start=(0.5, 0.5)) -> None:
    box = page.locator(selector).bounding_box()
    x, y = box["x"] + start[0] * box["width"], box["y"] + start[1] * box["height"]
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx, y + dy, steps=8)
    page.mouse.up()


def send_file_event(page, kind: str, path: Path, media_type: str = "image/jpeg") -> None:
    """A drop on the drop zone or a paste, carrying the file, as the browser makes them."""
    page.evaluate(
        """([kind, data, name, type]) => {
            const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
            const transfer = new DataTransfer();
            transfer.items.add(new File([bytes], name, {type}));
            const options = {bubbles: true, cancelable: true};
            if (kind === "drop") {
                const drop = new DragEvent("drop", {...options, dataTransfer: transfer});
                document.getElementById("drop").dispatchEvent(drop);
            } else {
                const paste = new ClipboardEvent("paste", {...options, clipboardData: transfer});
                document.body.dispatchEvent(paste);
            }
        }""",
        [kind, base64.b64encode(path.read_bytes()).decode(), path.name, media_type],
    )


@pytest.mark.slow
def test_a_photo_gets_its_pose_drawn_in_2d_and_3d(open_page, site, photo):
    page = open_page(site)
    assert page.locator("#run").is_disabled()
    page.set_input_files("#file", str(photo))
    wait_answers(page, 1)
    assert page.locator("#error").is_hidden()
    # What the drawing code drew: 14 joints of one person, on the photo and in 3D.
    assert page.get_attribute("#view2d", "data-joints") == "14"
    assert page.get_attribute("#view2d", "data-people") == "1"
    assert view3d(page)["joints"] == 14
    facts = page.inner_text("#facts")
    assert "Joint set" in facts and "Facing" in facts and photo.name in facts
    assert "total" in page.inner_text("#timings")
    if target := os.environ.get(SCREENSHOT_ENV):
        page.screenshot(path=target)

    first = pixels(page)
    assert first["drawn"] > 0.01, first  # grid, axes and skeleton on the background
    # Dragging turns the view; so do the arrow keys; the wheel and +/- zoom; 0 resets.
    start = view3d(page)
    drag(page, "#view3d", 120, 40)
    turned = view3d(page)
    assert turned["yaw"] != start["yaw"] and turned["pitch"] > start["pitch"]
    assert pixels(page)["changed"] > 0.005
    page.focus("#view3d")
    page.keyboard.press("ArrowRight")
    assert view3d(page)["yaw"] == pytest.approx(turned["yaw"] + 10)
    assert pixels(page)["changed"] > 0.005
    page.keyboard.press("+")
    assert view3d(page)["distance"] < turned["distance"]
    box = page.locator("#view3d").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.wheel(0, 400)
    assert view3d(page)["distance"] > turned["distance"]
    page.keyboard.press("0")
    assert view3d(page) == start

    # Every person: the answer's people, each drawn.
    page.check("#all-people")
    wait_answers(page, 2)
    people = int(page.get_attribute("#view2d", "data-people"))
    assert people >= 1 and page.get_attribute("#view2d", "data-joints") == str(14 * people)
    assert f"People found\n{people}" in page.inner_text("#facts")
    with page.expect_download() as download:
        page.click("#download")
    answer = json.loads(Path(download.value.path()).read_text())
    assert len(answer["people"]) == people and len(answer["people"][0]["joints_3d"]) == 14

    # A box dragged around the person is sent along: the answer is then the boxed person's.
    page.uncheck("#all-people")
    wait_answers(page, 3)
    shown = page.locator("#view2d").bounding_box()
    drag(page, "#view2d", 0.9 * shown["width"], 0.9 * shown["height"], start=(0.05, 0.05))
    wait_answers(page, 4)
    x0, y0, x1, y1 = json.loads(page.input_value("#bbox"))
    assert 0 <= x0 < x1 and 0 <= y0 < y1
    assert page.get_attribute("#view2d", "data-joints") == "14"
    assert "Person found\nyes" in page.inner_text("#facts")


# The bounding box of the skeletons in the 3D view, as fractions of the canvas: its pixels of a
# strong colour (the limbs' and joints'; the grid, the axes and the text are grey).
SKELETONS_JS = """canvas => {
    const data = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
    let x0 = canvas.width, y0 = canvas.height, x1 = -1, y1 = -1;
    for (let i = 0; i < data.length; i += 4) {
        const [r, g, b] = [data[i], data[i + 1], data[i + 2]];
        if (Math.max(r, g, b) - Math.min(r, g, b) < 80) continue;
        const x = (i / 4) % canvas.width, y = Math.floor(i / 4 / canvas.width);
        [x0, x1, y0, y1] = [Math.min(x0, x), Math.max(x1, x), Math.min(y0, y), Math.max(y1, y)];
    }
    return {width: (x1 - x0 + 1) / canvas.width, height: (y1 - y0 + 1) / canvas.height};
}"""


@pytest.fixture(scope="module")
def two_people(data_dir, tmp_path_factory) -> Path:
    """A 640 x 480 PNG of two LSP test people, a metre or more apart where they are placed."""
    import numpy as np
    from PIL import Image

    from ds3d.data.lsp import load_lsp
    from ds3d.evaluation.canvases import compose

    canvas = compose(load_lsp(split="test"), [3, 8], [0.8, 0.5], np.random.default_rng(0))
    path = tmp_path_factory.mktemp("canvas") / "two.png"
    Image.fromarray(canvas.image).save(path)
    return path


def facing_said(p: float) -> str:
    """What the page says of P(faces the camera) p: the way, where the model is sure."""
    way = "the camera" if p >= 0.5 else "away"
    return f"faces {way}" if max(p, 1 - p) >= 0.8 else f"unsure ({round(100 * max(p, 1 - p))} %"


@pytest.mark.slow
def test_the_3d_view_frames_the_people_found(open_page, site, photo, two_people):
    """At the default view, one person fills most of the 3D view's height (at first, on a 3 m
    grid, a quarter of it), and several people all show; the facing said is the answer's."""
    page = open_page(site)
    page.set_input_files("#file", str(photo))
    wait_answers(page, 1)
    extent = page.eval_on_selector("#view3d", SKELETONS_JS)
    assert extent["height"] >= 0.5, extent
    answer = httpx.post(f"{site}/v1/pose", files={"image": (photo.name, photo.read_bytes())})
    assert facing_said(answer.json()["facing_camera"]) in page.inner_text("#facts")

    page.check("#all-people")
    wait_answers(page, 2)
    page.set_input_files("#file", str(two_people))
    wait_answers(page, 3)
    assert page.get_attribute("#view2d", "data-people") == "2"
    assert view3d(page)["joints"] == 28  # every joint of both on the canvas
    extent = page.eval_on_selector("#view3d", SKELETONS_JS)
    assert max(extent.values()) >= 0.4, extent


@pytest.mark.slow
def test_the_api_error_is_shown_in_its_own_words(open_page, site, tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("not a photo\n")
    # What the API says of such a file, asked directly.
    refusal = httpx.post(f"{site}/v1/pose", files={"image": (notes.name, notes.read_bytes())})
    assert refusal.status_code == 422
    message = refusal.json()["error"]["message"]
    page = open_page(site)
    page.set_input_files("#file", str(notes))
    wait_answers(page, 1)
    shown = page.inner_text("#error")
    assert message in shown and "HTTP 422" in shown, shown
    assert page.get_attribute("#view2d", "data-joints") == "0"
    assert page.locator("#download").is_disabled()


@pytest.mark.slow
def test_the_camera_button_shows_where_there_is_a_camera_api(open_page, site):
    assert open_page(site).locator("#camera-open").is_visible()
    page = open_page(site)
    # A browser without one (or a page over plain http from another host).
    page.context.add_init_script("Object.defineProperty(navigator, 'mediaDevices', {})")
    page.reload()
    assert page.locator("#camera-open").is_hidden()
    assert page.locator("label[for=file]").is_visible()


@pytest.mark.slow
def test_a_deployment_with_keys_asks_for_one(open_page, engine, serving, photo):
    with serving(engine, api_keys=KEY, max_wait_ms=5) as url:
        page = open_page(url)  # the page itself needs no key
        send_file_event(page, "drop", photo)
        wait_answers(page, 1)
        assert "no API key" in page.inner_text("#error")
        assert page.locator("#key-details").get_attribute("open") is not None
        assert page.evaluate("document.activeElement.id") == "api-key"
        page.fill("#api-key", KEY)
        page.click("#run")
        wait_answers(page, 2)
        assert page.locator("#error").is_hidden()
        assert page.get_attribute("#view2d", "data-joints") == "14"
        # Kept for the tab only, and there after a reload.
        assert page.evaluate("[sessionStorage.length, localStorage.length]") == [1, 0]
        page.reload()
        assert page.input_value("#api-key") == KEY


@pytest.mark.slow
def test_the_page_fits_a_phone(open_page, site, photo):
    page = open_page(
        site,
        viewport={"width": 390, "height": 844},
        device_scale_factor=2,
        is_mobile=True,
        has_touch=True,
    )
    send_file_event(page, "paste", photo)
    wait_answers(page, 1)
    assert page.get_attribute("#view2d", "data-joints") == "14"
    assert page.evaluate("document.documentElement.scrollWidth") <= 390
    for selector in ("#view2d", "#view3d", "#timings", "#facts", "#drop"):
        box = page.locator(selector).bounding_box()
        assert box["x"] >= 0 and box["x"] + box["width"] <= 390, selector
    # Two fingers spreading apart zoom in.
    before = view3d(page)["distance"]
    page.eval_on_selector(
        "#view3d",
        """canvas => {
            const r = canvas.getBoundingClientRect();
            const [cx, cy] = [r.left + r.width / 2, r.top + r.height / 2];
            const touch = (type, id, x) => canvas.dispatchEvent(new PointerEvent(type,
                {pointerId: id, pointerType: "touch", clientX: x, clientY: cy, bubbles: true}));
            touch("pointerdown", 11, cx - 20); touch("pointerdown", 12, cx + 20);
            touch("pointermove", 12, cx + 60); touch("pointerup", 11, cx - 20);
            touch("pointerup", 12, cx + 60);
        }""",
    )
    assert view3d(page)["distance"] < before
    # The webcam (chromium's fake one): a frame taken is sent like a photo.
    page.click("#camera-open")
    page.wait_for_selector("#camera:not([hidden])")
    page.wait_for_function("() => document.getElementById('video').videoWidth > 0")
    page.click("#camera-snap")
    wait_answers(page, 2)
    assert page.locator("#camera").is_hidden()
    assert page.get_attribute("#view2d", "data-joints") == "14"
    assert "camera.jpg" in page.inner_text("#facts")


def test_the_legend_is_drawn_in_the_services_colours(open_page, site):
    """The page keeps no copy of the skeleton: its colours, like its limbs, come from
    GET /v1/skeleton (ds3d.viz.overlay's)."""
    colours = httpx.get(f"{site}/v1/skeleton").json()["colours"]
    page = open_page(site)
    for side in ("right", "left", "centre"):
        selector = f".swatch.{side}"
        colour = "s => getComputedStyle(document.querySelector(s), '::before').backgroundColor"
        # transparent until the page has the skeleton
        page.wait_for_function(f"s => ({colour})(s) !== 'rgba(0, 0, 0, 0)'", arg=selector)
        shown = page.evaluate(colour, selector)
        assert shown == "rgb({}, {}, {})".format(*colours[side]), side
