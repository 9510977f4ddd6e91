"""Python client SDK of the ds3d service: `PoseClient` and its async twin `AsyncPoseClient`.

Depends on httpx and numpy only (no torch, faiss or fastapi), so it installs anywhere (a person
box given with an image file also reads the file's size with Pillow):

    with PoseClient("http://127.0.0.1:8000") as client:  # api_key=..., default $DS3D_API_KEY
        res = client.lift(joints_2d)            # (14, 2) or (B, 14, 2) pixels
        res.joints_3d                           # (B, 14, 3) float32, millimetres
        pose = client.estimate("person.jpg")    # path, image bytes, or (H, W, 3) uint8 RGB array
        pose.joints_2d, pose.joints_3d          # (14, 2) pixels, (14, 3) millimetres

Both clients share one sans-IO core (`_Protocol`: build a request, parse a response, decide on a
retry); they differ only in how they send and sleep. A 503 (queue full, shutting down), a 429
(this caller over its rate or its share of the queue), a 502 (a load balancer found no replica)
or a connection that failed before the answer (refused, reset, closed by a replica that died) is
retried with exponential backoff, honouring the server's Retry-After: every endpoint is a pure
function of its request, so sending one twice is safe.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import random
import struct
import time
import zlib
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

RETRIED_STATUSES = frozenset({429, 502, 503})
# The connection failed before an answer came; timeouts are not retried (the server is busy).
RETRIED_ERRORS = (httpx.ConnectError, httpx.ReadError, httpx.WriteError, httpx.RemoteProtocolError)

ImageLike = str | Path | bytes | np.ndarray


class ServiceError(Exception):
    """The service answered with an error: HTTP status, its error code and message."""

    def __init__(self, status: int, code: str, message: str, retry_after: float | None = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.retry_after = status, code, message, retry_after


@dataclass(frozen=True)
class LiftResult:
    """3D poses of B 2D poses, in the order sent (the plain form of ds3d.lifter.LiftResult)."""

    joints_3d: np.ndarray  # (B, 14, 3) float32, millimetres
    bone_lengths: np.ndarray  # (B, 14) float32, millimetres, in bone_names order
    joint_set: list[str]  # (B,) the joint set each pose was fitted with
    energy: np.ndarray  # (B,) float32, final fit energy
    joint_names: list[str]
    bone_names: list[str]
    model: str
    timings_ms: dict[str, float] = field(default_factory=dict)
    # (B, 3) float32 mm: the hip midpoints in the camera's coordinates of the poses sent with
    # intrinsics (NaN rows for the others); None when none was
    root_position: np.ndarray | None = None


@dataclass(frozen=True)
class Person:
    """2D and 3D pose of one person in an image: the best one (estimate), or one of every
    person found (find_people); the plain form of the service's Person (ds3d.result.Person)."""

    joints_2d: np.ndarray  # (14, 2) float32, pixels of the image sent
    joints_3d: np.ndarray  # (14, 3) float32, millimetres
    confidence: np.ndarray  # (14,) float32 in [0, 1]
    facing_camera: float  # P(faces the camera); below 0.5 left and right were swapped
    joint_set: str
    joint_names: list[str]
    model: str
    timings_ms: dict[str, float] = field(default_factory=dict)
    box: np.ndarray | None = None  # (4,) float32 x0, y0, x1, y1 pixels, the joints' box
    score: float | None = None  # probability in [0, 1] that it is a person
    person_found: bool = True  # estimate(): false when nobody scored min_score
    # Where the person stands: the hip midpoint (3,) float32 mm in the camera's coordinates,
    # the joints there (14, 3), and the focal length (px) that placed them, assumed or given.
    root_position: np.ndarray | None = None
    joints_3d_camera: np.ndarray | None = None
    focal_px: float | None = None
    focal_assumed: bool | None = None
    # asked with angles=True: the joint angles for animation tools, as the API answers them
    # (ds3d_service.schemas.JointAngles: nodes, parents, offsets, root, rotations as quaternions)
    angles: dict | None = None


# The name Person had before it took the name of the service's and the library's type.
PoseResult = Person


@dataclass(frozen=True)
class _Request:
    method: str
    path: str
    kwargs: dict


def encode_png(image: np.ndarray) -> bytes:
    """(H, W, 3) or (H, W) uint8 -> PNG bytes (no compression filter; zlib level 6)."""
    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"need an (H, W, 3) or (H, W) uint8 array, got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    color_type = 2 if img.ndim == 3 else 0
    rows = img.reshape(h, -1)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    header = struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )


_MAGIC = (
    (b"\xff\xd8\xff", "image/jpeg"),
    (b"\x89PNG", "image/png"),
    (b"BM", "image/bmp"),
    (b"GIF8", "image/gif"),
    (b"RIFF", "image/webp"),
)


def _image_bytes(image: ImageLike) -> tuple[bytes, str]:
    """(file bytes, content type) of a path, raw bytes or an RGB uint8 array."""
    if isinstance(image, np.ndarray):
        return encode_png(image), "image/png"
    data = Path(image).read_bytes() if isinstance(image, str | Path) else bytes(image)
    ctype = next((t for magic, t in _MAGIC if data.startswith(magic)), "application/octet-stream")
    return data, ctype


def person_box(bbox, width: int, height: int) -> dict[str, float]:
    """A person box's corners x0, y0, x1, y1 px on an image of width x height px -> /v1/pose's
    `box`: its centre cx, cy and its width and height as fractions of the image's. Raises
    ValueError for corners that are not in order (x1 > x0, y1 > y0) or not finite."""
    x0, y0, x1, y1 = (float(v) for v in np.asarray(bbox, dtype=np.float64).reshape(4))
    if not (x1 > x0 and y1 > y0 and np.isfinite([x0, y0, x1, y1]).all()):
        raise ValueError(
            f"bbox [{x0:g}, {y0:g}, {x1:g}, {y1:g}] wants x1 > x0 and y1 > y0 (corners x0, y0, "
            "x1, y1, not x, y, width, height)"
        )
    return {
        "cx": (x0 + x1) / 2 / width,
        "cy": (y0 + y1) / 2 / height,
        "width": (x1 - x0) / width,
        "height": (y1 - y0) / height,
    }


# EXIF orientations that turn an image by a quarter: its upright width is its stored height.
_QUARTER_TURNS = frozenset({5, 6, 7, 8})


def _upright_size(image: ImageLike, data: bytes) -> tuple[int, int]:
    """(width, height) px of the image as the service reads it, upright: an array's shape, or
    a file's header turned by its EXIF orientation (read with Pillow, imported here only)."""
    if isinstance(image, np.ndarray):
        return image.shape[1], image.shape[0]
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            width, height = img.size
            turned = img.getexif().get(0x0112) in _QUARTER_TURNS  # 0x0112: Orientation
    except UnidentifiedImageError as err:
        raise ValueError(f"a box needs its image's size, and this is not an image: {err}") from err
    return (height, width) if turned else (width, height)


def _retry_after(resp: httpx.Response) -> float | None:
    value = resp.headers.get("retry-after")
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:  # an HTTP date: fall back to our own backoff
        return None


class _Protocol:
    """Requests, responses and the retry policy, shared by the sync and async clients."""

    def __init__(self, retries: int, backoff_s: float, max_backoff_s: float):
        self.retries, self.backoff_s, self.max_backoff_s = retries, backoff_s, max_backoff_s

    def lift_request(self, joints_2d, intrinsics=None, visible=None) -> _Request:
        joints = np.asarray(joints_2d, dtype=np.float64)
        if joints.ndim == 2:
            joints = joints[None]
        if joints.ndim != 3 or joints.shape[-1] != 2:
            raise ValueError(f"joints_2d must be (14, 2) or (B, 14, 2), got {joints.shape}")
        b = joints.shape[0]
        ks = None if intrinsics is None else np.broadcast_to(np.asarray(intrinsics), (b, 3, 3))
        vis = (
            None
            if visible is None
            else np.broadcast_to(np.asarray(visible, bool), joints.shape[:2])
        )
        items = []
        for i in range(b):
            item: dict = {"joints_2d": joints[i].tolist()}
            if ks is not None:
                item["intrinsics"] = np.asarray(ks[i], dtype=np.float64).tolist()
            if vis is not None:
                item["visible"] = vis[i].tolist()
            items.append(item)
        return _Request("POST", "/v1/lift", {"json": {"items": items}})

    def pose_request(
        self,
        image: ImageLike,
        bbox=None,
        intrinsics=None,
        people: str = "best",
        min_score: float | None = None,
        focal_px: float | None = None,
        angles: bool = False,
    ) -> _Request:
        data, ctype = _image_bytes(image)
        query: dict = {"people": people}
        if angles:
            query["angles"] = "true"
        if min_score is not None:
            query["min_score"] = float(min_score)
        if focal_px is not None:
            query["focal_px"] = float(focal_px)
        form = {}
        if bbox is not None:
            form["box"] = json.dumps(person_box(bbox, *_upright_size(image, data)))
        if intrinsics is not None:
            form["intrinsics"] = str(
                np.asarray(intrinsics, dtype=np.float64).reshape(3, 3).tolist()
            )
        files = {"image": ("image", data, ctype)}
        return _Request("POST", "/v1/pose", {"files": files, "data": form, "params": query})

    @staticmethod
    def raise_for_error(resp: httpx.Response) -> None:
        if resp.is_success:
            return
        try:
            err = resp.json()["error"]
            code, message = str(err["code"]), str(err["message"])
        except (ValueError, KeyError, TypeError):
            code, message = f"http_{resp.status_code}", resp.text[:200]
        raise ServiceError(resp.status_code, code, message, _retry_after(resp))

    def parse_lift(self, resp: httpx.Response) -> LiftResult:
        self.raise_for_error(resp)
        body = resp.json()
        items = body["items"]
        return LiftResult(
            joints_3d=np.asarray([it["joints_3d"] for it in items], dtype=np.float32),
            bone_lengths=np.asarray([it["bone_lengths"] for it in items], dtype=np.float32),
            joint_set=[it["joint_set"] for it in items],
            energy=np.asarray([it["energy"] for it in items], dtype=np.float32),
            joint_names=list(body["joint_names"]),
            bone_names=list(body["bone_names"]),
            model=body["model"],
            timings_ms=dict(body.get("timings_ms", {})),
            root_position=_placed_roots(items),
        )

    def parse_pose(self, resp: httpx.Response) -> Person:
        self.raise_for_error(resp)
        body = resp.json()
        return _person(body, body, bool(body.get("person_found", True)))

    def parse_people(self, resp: httpx.Response) -> list[Person]:
        self.raise_for_error(resp)
        body = resp.json()
        return [_person(person, body, True) for person in body["people"]]

    def retry_delay(self, attempt: int, resp: httpx.Response | None) -> float | None:
        """Seconds to wait before retry number attempt + 1, or None to stop: retry a 429, a 502,
        a 503 or a failed connection (resp None) up to `retries` times; Retry-After wins over the
        backoff."""
        if attempt >= self.retries or (
            resp is not None and resp.status_code not in RETRIED_STATUSES
        ):
            return None
        backoff = min(self.max_backoff_s, self.backoff_s * 2**attempt) * random.uniform(0.5, 1.0)
        hinted = _retry_after(resp) if resp is not None else None
        return min(self.max_backoff_s, hinted) if hinted is not None else backoff


def _placed_roots(items: list[dict]) -> np.ndarray | None:
    """/v1/lift items' root positions (B, 3), NaN for an item without; None if none has one."""
    roots = [it.get("root_position") for it in items]
    if all(root is None for root in roots):
        return None
    return np.asarray([[np.nan] * 3 if r is None else r for r in roots], dtype=np.float32)


def _array_or_none(person: dict, name: str) -> np.ndarray | None:
    """A field of a person as a float32 array, or None from a server that does not answer it."""
    return np.asarray(person[name], dtype=np.float32) if name in person else None


def _person(person: dict, body: dict, found: bool) -> Person:
    """One person of a /v1/pose answer (`body`: its shared fields)."""
    return Person(
        joints_2d=np.asarray(person["joints_2d"], dtype=np.float32),
        joints_3d=np.asarray(person["joints_3d"], dtype=np.float32),
        confidence=np.asarray(person["confidence"], dtype=np.float32),
        facing_camera=float(person["facing_camera"]),
        joint_set=person["joint_set"],
        joint_names=list(body["joint_names"]),
        model=body["model"],
        timings_ms=dict(body.get("timings_ms", {})),
        box=np.asarray(person["box"], dtype=np.float32) if "box" in person else None,
        score=float(person["score"]) if "score" in person else None,
        person_found=found,
        root_position=_array_or_none(person, "root_position"),
        joints_3d_camera=_array_or_none(person, "joints_3d_camera"),
        focal_px=float(person["focal_px"]) if "focal_px" in person else None,
        focal_assumed=bool(person["focal_assumed"]) if "focal_assumed" in person else None,
        angles=person.get("angles"),
    )


def auth_headers(api_key: str | None) -> dict[str, str]:
    """The Authorization header of `api_key`, else of $DS3D_API_KEY; none without either."""
    key = api_key if api_key is not None else os.environ.get("DS3D_API_KEY")
    return {"Authorization": f"Bearer {key}"} if key else {}


class PoseClient:
    """Blocking client. api_key: sent as `Authorization: Bearer KEY` (default $DS3D_API_KEY;
    none when neither is set). timeout: seconds per HTTP request; retries: extra tries on a 429,
    a 502, a 503 or a failed connection, waiting backoff_s * 2**attempt (jittered, at most
    max_backoff_s) or the server's Retry-After; transport: an httpx transport (e.g. a Unix
    socket), default TCP."""

    def __init__(
        self,
        base_url: str,
        timeout: float = 30.0,
        retries: int = 3,
        backoff_s: float = 0.1,
        max_backoff_s: float = 10.0,
        transport: httpx.BaseTransport | None = None,
        api_key: str | None = None,
    ):
        self._proto = _Protocol(retries, backoff_s, max_backoff_s)
        self._http = httpx.Client(
            base_url=base_url, timeout=timeout, transport=transport, headers=auth_headers(api_key)
        )

    def _send(self, req: _Request, parse):
        attempt = 0
        while True:
            try:
                resp = self._http.request(req.method, req.path, **req.kwargs)
            except RETRIED_ERRORS:
                if (delay := self._proto.retry_delay(attempt, None)) is None:
                    raise
            else:
                if (delay := self._proto.retry_delay(attempt, resp)) is None:
                    return parse(resp)
            time.sleep(delay)
            attempt += 1

    def lift(self, joints_2d, intrinsics=None, visible=None) -> LiftResult:
        """joints_2d (14, 2) or (B, 14, 2) pixels; intrinsics (3, 3) or (B, 3, 3); visible (14,)
        or (B, 14) bool -> LiftResult with joints_3d (B, 14, 3) mm. One request: B is at most
        the server's queue size (DS3D_MAX_QUEUE, default 64), else ServiceError 413."""
        req = self._proto.lift_request(joints_2d, intrinsics, visible)
        return self._send(req, self._proto.parse_lift)

    def estimate(
        self,
        image: ImageLike,
        bbox=None,
        intrinsics=None,
        focal_px: float | None = None,
        angles: bool = False,
    ) -> Person:
        """image: a path, image file bytes, or an (H, W, 3) uint8 RGB array; bbox (4,) x0, y0,
        x1, y1 pixels of the upright image (sent as the API's box, person_box); intrinsics
        (3, 3); focal_px: without intrinsics, the camera's focal
        length in pixels, which places the person (Person.root_position; default assumed);
        angles: also the joint angles (Person.angles)."""
        req = self._proto.pose_request(image, bbox, intrinsics, focal_px=focal_px, angles=angles)
        return self._send(req, self._proto.parse_pose)

    def find_people(
        self,
        image: ImageLike,
        intrinsics=None,
        min_score: float | None = None,
        focal_px: float | None = None,
        angles: bool = False,
    ) -> list[Person]:
        """Every person in the image scoring at least min_score (default: the server's),
        best first; [] when nobody does. Other arguments as estimate."""
        req = self._proto.pose_request(image, None, intrinsics, "all", min_score, focal_px, angles)
        return self._send(req, self._proto.parse_people)

    def estimate_many(self, images: Iterable[ImageLike], concurrency: int = 8) -> list[Person]:
        """estimate() of each image, `concurrency` requests in flight; results in order."""
        with ThreadPoolExecutor(max(1, concurrency)) as pool:
            return list(pool.map(self.estimate, images))

    def healthy(self) -> bool:
        return self._http.get("/healthz").status_code == 200

    def ready(self) -> bool:
        return self._http.get("/readyz").status_code == 200

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> PoseClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class AsyncPoseClient:
    """The asyncio twin of PoseClient (same arguments, same results, awaitable methods)."""

    def __init__(
        self,
        base_url: str,
        timeout: float = 30.0,
        retries: int = 3,
        backoff_s: float = 0.1,
        max_backoff_s: float = 10.0,
        transport: httpx.AsyncBaseTransport | None = None,
        api_key: str | None = None,
    ):
        self._proto = _Protocol(retries, backoff_s, max_backoff_s)
        self._http = httpx.AsyncClient(
            base_url=base_url, timeout=timeout, transport=transport, headers=auth_headers(api_key)
        )

    async def _send(self, req: _Request, parse):
        attempt = 0
        while True:
            try:
                resp = await self._http.request(req.method, req.path, **req.kwargs)
            except RETRIED_ERRORS:
                if (delay := self._proto.retry_delay(attempt, None)) is None:
                    raise
            else:
                if (delay := self._proto.retry_delay(attempt, resp)) is None:
                    return parse(resp)
            await asyncio.sleep(delay)
            attempt += 1

    async def lift(self, joints_2d, intrinsics=None, visible=None) -> LiftResult:
        req = self._proto.lift_request(joints_2d, intrinsics, visible)
        return await self._send(req, self._proto.parse_lift)

    async def estimate(
        self,
        image: ImageLike,
        bbox=None,
        intrinsics=None,
        focal_px: float | None = None,
        angles: bool = False,
    ) -> Person:
        req = self._proto.pose_request(image, bbox, intrinsics, focal_px=focal_px, angles=angles)
        return await self._send(req, self._proto.parse_pose)

    async def find_people(
        self,
        image: ImageLike,
        intrinsics=None,
        min_score: float | None = None,
        focal_px: float | None = None,
        angles: bool = False,
    ) -> list[Person]:
        req = self._proto.pose_request(image, None, intrinsics, "all", min_score, focal_px, angles)
        return await self._send(req, self._proto.parse_people)

    async def estimate_many(
        self, images: Sequence[ImageLike], concurrency: int = 8
    ) -> list[Person]:
        gate = asyncio.Semaphore(max(1, concurrency))

        async def one(image):
            async with gate:
                return await self.estimate(image)

        return list(await asyncio.gather(*(one(im) for im in images)))

    async def healthy(self) -> bool:
        return (await self._http.get("/healthz")).status_code == 200

    async def ready(self) -> bool:
        return (await self._http.get("/readyz")).status_code == 200

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncPoseClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()
