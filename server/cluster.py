"""The server's connection to a Ray cluster (job_backend / render_backend ``ray``).

Ray is imported lazily: with the ``local`` backends nothing imports it, and it is an optional
extra (``pip install telesplat[cluster]``). One connection per process, shared by the job and
render backends; :func:`connect` is idempotent.

Authentication is Ray's own: Ray 2.60 runs token auth by default (``RAY_AUTH_MODE=token``); the
head and every client read the token from ``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or
``~/.ray/auth_token`` (docs/scale.md). A private Ray ('auto') listens on every interface and
runs whatever it is sent, so it is refused without token auth unless the setting
``cluster_allow_no_auth`` says otherwise; an external cluster without it gets a warning.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.config import Settings

log = logging.getLogger(__name__)

NAMESPACE = "telesplat"
AUTH_MODE_ENV = "RAY_AUTH_MODE"


class ClusterAuthDisabled(RuntimeError):
    """A private Ray would run without token auth, and the settings do not allow it."""
LOCAL_ADDRESS = "auto"  # cluster_address that starts a private Ray on this machine

_lock = threading.Lock()
_connected_to: str | None = None


def available() -> bool:
    """Whether ray is importable (the ``cluster`` extra is installed)."""
    return importlib.util.find_spec("ray") is not None


def connect(settings: Settings) -> None:
    """Connect this process to ``settings.cluster_address`` (or start a local Ray for 'auto').

    Idempotent: a second call with the same address does nothing; another address is an error
    (one process, one cluster).
    """
    global _connected_to
    address = settings.cluster_address
    if not address:
        raise ValueError("cluster_address is not set (host:port of a Ray head, or 'auto')")
    if not available():
        raise RuntimeError("the ray backends need ray: pip install 'telesplat[cluster]'")
    import ray

    with _lock:
        if _connected_to is not None and ray.is_initialized():
            if _connected_to != address:
                raise RuntimeError(f"already connected to Ray at {_connected_to}, "
                                   f"not {address}")
            return
        common = {"namespace": NAMESPACE, "log_to_driver": False,
                  "configure_logging": False, "ignore_reinit_error": True}
        _token_auth_if_token_available()
        if address == LOCAL_ADDRESS:
            _refuse_no_auth(settings)
            # A fresh single-machine cluster owned by this process. Ray listens on every
            # interface (it advertises the machine's address even when asked for 127.0.0.1):
            # its token auth, on by default, is what keeps others out.
            ray.init(address="local", include_dashboard=False,
                     object_store_memory=settings.cluster_object_store_bytes, **common)
            if not token_auth_enabled() and not settings.cluster_allow_no_auth:
                ray.shutdown()
                raise ClusterAuthDisabled(_NO_AUTH)
        else:
            ray.init(address=address, **common)
            if not token_auth_enabled():
                log.warning("the Ray cluster at %s runs without token auth: anyone who can "
                            "reach it can run code there and read its data (set "
                            "RAY_AUTH_MODE=token on the head and here; docs/scale.md)", address)
        _connected_to = address


_NO_AUTH = ("refusing to start a private Ray (cluster_address 'auto') without token auth: it "
            "listens on every interface and runs whatever it is sent. Unset "
            f"{AUTH_MODE_ENV} (Ray's default is token auth) or set it to 'token'; or set "
            "cluster_allow_no_auth = true to accept the risk on a closed network.")


def _refuse_no_auth(settings: Settings) -> None:
    """Before a private Ray starts: an explicit RAY_AUTH_MODE other than token is refused
    unless cluster_allow_no_auth (Ray's default, unset, is token auth)."""
    mode = os.environ.get(AUTH_MODE_ENV)
    if mode is not None and mode.lower() != "token" and not settings.cluster_allow_no_auth:
        raise ClusterAuthDisabled(_NO_AUTH)
    if mode is not None and mode.lower() != "token":
        log.warning("starting a private Ray without token auth (cluster_allow_no_auth)")


def token_auth_enabled() -> bool:
    """Whether this process runs Ray with token auth (after ray.init)."""
    from ray._private.authentication.authentication_utils import is_token_auth_enabled

    return bool(is_token_auth_enabled())


def _token_auth_if_token_available() -> None:
    """Use token auth when a token is at hand and RAY_AUTH_MODE is unset.

    Ray does this itself for a local cluster found automatically, but not for an explicit
    address, where a head started with token auth (Ray 2.60's default) would refuse us.
    """
    if os.environ.get("RAY_AUTH_MODE") is not None:
        return  # an explicit choice (token / disabled) is the deployment's
    from ray._private.authentication import authentication_token_setup as token_setup

    token_setup.maybe_enable_token_auth_if_token_available(warn_if_disabled=False)


def connected() -> bool:
    if _connected_to is None or not available():
        return False
    import ray

    return ray.is_initialized()


def shutdown() -> None:
    """Disconnect (and stop the local Ray that 'auto' started); harmless when not connected."""
    global _connected_to
    with _lock:
        if _connected_to is None:
            return
        import ray

        ray.shutdown()
        _connected_to = None
