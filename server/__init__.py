"""The FastAPI service: streaming sessions, avatar registry, jobs and auth.

Filled in by the streaming-service issue.
"""

# Before anything loads torch or numba: their thread pools wait passively (a value already in
# the environment wins); `python -m server` and uvicorn's import of server.app come here first.
from avatar_core.threads import passive_waiting as _passive_waiting  # noqa: E402

_passive_waiting()
