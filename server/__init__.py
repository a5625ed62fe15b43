"""The FastAPI service: streaming sessions, avatar registry, jobs and auth.

Filled in by the streaming-service issue.
"""
