"""The HTTP routes, one APIRouter per resource; `ROUTERS` is what `create_app` includes, in the
order their paths appear in the OpenAPI."""

from __future__ import annotations

from ds3d_service.routes import health, lift, page, pose, skeleton

API_ROUTERS = (lift.router, pose.router)  # the /v1 API, which callers may need a key for
# /v1/skeleton is open: the page draws with it before any key is given
ROUTERS = (*API_ROUTERS, skeleton.router, health.router, page.router)
