"""The HTTP routes, one APIRouter per resource; `ROUTERS` is what `create_app` includes, in the
order their paths appear in the OpenAPI."""

from __future__ import annotations

from service.routes import health, lift, page, pose

API_ROUTERS = (lift.router, pose.router)  # the /v1 API, which callers may need a key for
ROUTERS = (*API_ROUTERS, health.router, page.router)
