"""The ds3d HTTP service: FastAPI app, micro-batching queue, schemas, settings, client SDK."""
