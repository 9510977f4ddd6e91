"""The HTTP routes, one APIRouter per resource; `ROUTERS` is what `create_app` includes, in the
order their paths appear in the OpenAPI."""

from __future__ import annotations

from service.routes import health, lift, pose

ROUTERS = (lift.router, pose.router, health.router)
