"""``telesplat serve`` (also ``python -m server``): run the streaming server with uvicorn.

``avatar_core.cli`` dispatches ``serve`` here with a lazy import, so the engine never imports
the server at module level.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # `telesplat --help` should not pay for importing FastAPI
    from fastapi import FastAPI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=None, help="interface (default from settings: "
                                                     "127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="TCP port (default 8000)")
    parser.add_argument("--config", type=Path, default=None, help="settings file (.toml/.json)")
    parser.add_argument("--data-dir", type=Path, default=None, help="avatars, tokens, jobs")
    parser.add_argument("--demo-avatar", default=None,
                        help="synthetic, trained, none or a package path")
    parser.add_argument("--body-models", type=Path, default=None,
                        help="body-model folder, official file names (setting body_models; "
                             "default: $TELESPLAT_BODY_MODELS, else the synthetic family)")
    parser.add_argument("--cluster", metavar="ADDRESS", default=None,
                        help="run training jobs and render workers on the Ray cluster at "
                             "ADDRESS (host:port of its head; 'auto': a local Ray); sets "
                             "job_backend, render_backend and cluster_address (docs/scale.md)")
    parser.add_argument("--log-level", default="info")
    parser.add_argument("--issue-token", metavar="SUBJECT:SCOPES", default=None,
                        help="add a token to the token store (e.g. alice:stream,train), print "
                             "it and exit")
    parser.add_argument("--rotate-local-token", action="store_true",
                        help="revoke the local admin token (auth = local), write a new one to "
                             "DATA_DIR/local_token, print it and exit")


def _announce(app: FastAPI, url: str) -> None:
    """Print the URL (with the local admin token) once start-up, warm-up included, is done.

    The token travels in the URL's fragment (``#token=``), which a browser never sends: it
    stays out of every request line and log; the page moves it into memory at once."""
    inner = app.router.lifespan_context

    @contextlib.asynccontextmanager
    async def announced(app: FastAPI) -> AsyncIterator[None]:
        async with inner(app):
            token = app.state.ctx.local_token
            if token:
                print(f"Telesplat is serving at {url}/#token={token}", flush=True)
                print(f"  admin token (subject 'local'): {token}", flush=True)
                print(f"  (the same at every start, kept in "
                      f"{app.state.ctx.settings.local_token_path}; "
                      f"telesplat serve --rotate-local-token replaces it)", flush=True)
            else:
                print(f"Telesplat is serving at {url}/ (tokens from "
                      f"{app.state.ctx.settings.tokens_path})", flush=True)
            links = app.state.ctx.startup_links
            for scope in ("watch", "perform"):
                if scope in links:
                    print(f"  {scope} link: {url}{links[scope]}", flush=True)
            build = app.state.ctx.demo_build
            if build is not None and build.status()["state"] == "building":
                print("  the trained demo avatar is being built in the background (the page "
                      f"shows its progress; {url}/v1/demo); the untrained one stands in",
                      flush=True)
            yield

    app.router.lifespan_context = announced


def serve(args: argparse.Namespace) -> int:
    import uvicorn

    from .app import create_app
    from .config import load_settings
    from .rooms.restart import RestartingServer
    from .stream.gate import handshake_check
    from .stream.net import listen_socket, websocket_protocol

    cluster = {} if not getattr(args, "cluster", None) else {
        "job_backend": "ray", "render_backend": "ray", "cluster_address": args.cluster}
    settings = load_settings(args.config, host=args.host, port=args.port,
                             data_dir=args.data_dir, demo_avatar=args.demo_avatar,
                             body_models=args.body_models, **cluster)
    if args.issue_token:
        from .auth import TokenStore

        subject, _, scopes = args.issue_token.partition(":")
        token = TokenStore(settings.tokens_path).issue(subject, scopes.split(",") or ["stream"])
        print(token)
        return 0
    if getattr(args, "rotate_local_token", False):
        from .auth import TokenStore, rotate_local_token
        from .private import private_dir

        private_dir(settings.data_dir)
        token = rotate_local_token(TokenStore(settings.tokens_path), settings.local_token_path)
        print(token, flush=True)
        print(f"telesplat serve: the local admin token in {settings.local_token_path} was "
              "replaced; the old one no longer works (a running server stops accepting it "
              "within tokens_reload_interval_s)", file=sys.stderr)
        return 0
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: "
                                                             "%(message)s")
    os.umask(0o077)  # what the server and its training processes write is theirs alone
    app = create_app(settings)
    sock = listen_socket(settings.host, settings.port, settings.send_buffer_bytes)
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    _announce(app, f"http://{host}:{sock.getsockname()[1]}")
    config = uvicorn.Config(app, log_level=args.log_level, lifespan="on",
                            ws=websocket_protocol(
                                settings.hello_max_bytes, handshake_check(app.state.ctx)),
                            ws_max_size=settings.limits.max_message_bytes + 1024,
                            timeout_graceful_shutdown=5)
    # SIGTERM: participants get error 'restarting' and close 1012 first (server/rooms/restart.py)
    RestartingServer(config, app.state.ctx).run(sockets=[sock])
    return 0


def register(groups: argparse._SubParsersAction) -> None:
    """``telesplat serve``: registered with the engine's CLI as a ``telesplat.commands`` entry
    point (pyproject.toml), so avatar_core never imports the server."""
    parser = groups.add_parser("serve", help="run the streaming server (FastAPI + uvicorn)")
    add_arguments(parser)
    parser.set_defaults(func=serve)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="telesplat serve", description=__doc__)
    add_arguments(parser)
    try:
        return serve(parser.parse_args(argv))
    except (ValueError, OSError) as exc:
        print(f"telesplat serve: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
