"""The FastAPI service: streaming sessions, avatar registry, jobs, auth (streaming-service issue)."""
