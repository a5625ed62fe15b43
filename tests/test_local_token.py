"""The local admin token (auth = "local") keeps its identity across restarts of one data dir:
its plain text in data_dir/local_token (0600), its hash in the token store; `telesplat serve
--rotate-local-token` (run here as a subprocess) replaces it. The start-up room's links printed
at each start keep working after a restart, and so do those printed before it. Real servers
(uvicorn on 127.0.0.1) on one data dir, one after the other.
"""

from __future__ import annotations

import logging
import os
import stat
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from server.app import create_app
from server.auth import LOCAL_SUBJECT, TokenStore, local_admin_token, read_local_token
from server.cli import main as cli_main
from server.config import Settings
from tests.server_fixtures import run_server, wait_until

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT_S = 30.0
FAST = {"warmup": False, "default_width": 64, "default_height": 64}


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def status(url: str, token: str, path: str = "/v1/rooms") -> int:
    with httpx.Client(base_url=url, timeout=TIMEOUT_S) as client:
        return client.get(path, headers={"Authorization": f"Bearer {token}"}).status_code


def rotate(data_dir: Path) -> subprocess.CompletedProcess:
    """`telesplat serve --rotate-local-token` as the user runs it (python -m server)."""
    return subprocess.run([sys.executable, "-m", "server", "--data-dir", str(data_dir),
                           "--rotate-local-token"], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def link_token(link: str) -> str:
    return link.split("#token=", 1)[1]


def test_the_local_token_and_the_startup_links_survive_a_restart(tmp_path):
    with run_server(tmp_path, **FAST) as first:
        token, links = first.token, dict(first.ctx.startup_links)
        assert status(first.url, token) == 200
    path = tmp_path / "local_token"
    assert path.read_text() == token + "\n" and mode(path) == 0o600
    assert mode(path.with_name("local_token.lock")) == 0o600
    stored = (tmp_path / "tokens.json").read_text()
    assert token not in stored  # the store keeps only its hash
    with run_server(tmp_path, **FAST) as second:
        assert second.token == token  # the link printed before the restart still opens
        assert status(second.url, token) == 200
        assert status(second.url, token, "/v1/jobs") == 200  # an admin: every scope
        again = second.ctx.startup_links
        assert again["room"] == links["room"]
        for scope in ("watch", "perform"):  # the links printed before and after the restart
            for link in (links[scope], again[scope]):
                assert link.startswith(f"/?room={links['room']}#token=tsr_")
                assert status(second.url, link_token(link), f"/v1/rooms/{links['room']}") == 200
                with httpx.Client(base_url=second.url, timeout=TIMEOUT_S) as client:
                    page = client.get(link.split("#")[0])  # what the browser asks for
                assert page.status_code == 200 and "<html" in page.text.lower()
        assert status(second.url, "tsk_" + "x" * 43) == 401
    assert mode(path) == 0o600 and read_local_token(path) == token


def test_rotation_revokes_the_old_token_also_in_a_running_server(tmp_path):
    with run_server(tmp_path, tokens_reload_interval_s=0.1, **FAST) as srv:
        old = srv.token
        assert status(srv.url, old) == 200
        done = rotate(tmp_path)
        assert done.returncode == 0, done.stderr
        new = done.stdout.strip()
        assert new.startswith("tsk_") and new != old
        assert "--rotate-local-token" not in done.stdout and "replaced" in done.stderr
        assert (tmp_path / "local_token").read_text() == new + "\n"
        assert mode(tmp_path / "local_token") == 0o600
        # The running server re-reads the store: the old token is refused, the new one works.
        wait_until(lambda: status(srv.url, old) == 401, 10, what="the old token refused")
        assert status(srv.url, new) == 200
    with run_server(tmp_path, **FAST) as restarted:  # the next start keeps the new one
        assert restarted.token == new
        assert status(restarted.url, new) == 200 and status(restarted.url, old) == 401


def _app(data_dir: Path, **settings):
    return create_app(Settings(data_dir=data_dir, demo_avatar="none", startup_room=False,
                               warmup=False, **settings))


def test_the_token_stays_in_create_app_and_other_local_tokens_go(tmp_path):
    first = _app(tmp_path).state.ctx.local_token
    store = TokenStore(tmp_path / "tokens.json")
    stray = store.issue(LOCAL_SUBJECT, ("stream",))  # e.g. --issue-token local:stream
    alice = store.issue("alice", ("stream",))
    ctx = _app(tmp_path).state.ctx
    assert ctx.local_token == first and ctx.tokens.principal(first).is_admin
    assert ctx.tokens.principal(stray) is None  # one live local token
    assert ctx.tokens.principal(alice) is not None
    # auth = "tokens" leaves the file alone and prints none.
    assert _app(tmp_path, auth="tokens").state.ctx.local_token is None
    assert read_local_token(tmp_path / "local_token") == first


def test_a_token_the_store_no_longer_knows_is_replaced(tmp_path, caplog):
    first = _app(tmp_path).state.ctx.local_token
    TokenStore(tmp_path / "tokens.json").revoke(first)  # revoked by hand
    with caplog.at_level(logging.WARNING, logger="server.auth"):
        second = _app(tmp_path).state.ctx.local_token
    assert second != first and read_local_token(tmp_path / "local_token") == second
    assert "not in the token store" in caplog.text and first not in caplog.text
    (tmp_path / "tokens.json").unlink()  # a store deleted: a new token, never the old one back
    third = _app(tmp_path).state.ctx.local_token
    assert third not in (first, second)


def test_a_file_others_may_read_is_made_private_with_a_warning(tmp_path, caplog):
    token = _app(tmp_path).state.ctx.local_token
    path = tmp_path / "local_token"
    os.chmod(path, 0o644)
    with caplog.at_level(logging.WARNING, logger="server.auth"):
        assert _app(tmp_path).state.ctx.local_token == token
    assert mode(path) == 0o600 and "rotate-local-token" in caplog.text


@pytest.mark.parametrize("content", [b"", b"hello\n", b"tsk_short\n", b"tsk_" + b"a" * 300,
                                     b"tsk_" + b"\xff" * 43, b"tsk_" + b"a" * 43 + b" extra"])
def test_a_damaged_file_is_a_clear_error_that_rotation_mends(tmp_path, content, capsys):
    path = tmp_path / "local_token"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="does not hold a Telesplat token.*rotate-local-token"):
        _app(tmp_path)
    # the CLI's own entry, in this process (a subprocess costs 5 s of imports; the one in
    # test_rotation_revokes_the_old_token_also_in_a_running_server runs it as users do)
    assert cli_main(["--data-dir", str(tmp_path), "--rotate-local-token"]) == 0
    assert _app(tmp_path).state.ctx.local_token == capsys.readouterr().out.strip()


def test_a_link_or_a_folder_in_its_place_is_refused(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_text("tsk_" + "a" * 43 + "\n")
    data = tmp_path / "data"
    data.mkdir()
    (data / "local_token").symlink_to(elsewhere)
    with pytest.raises(ValueError, match="cannot read the local token"):
        local_admin_token(TokenStore(data / "tokens.json"), data / "local_token")
    (data / "local_token").unlink()
    (data / "local_token").mkdir()
    with pytest.raises(ValueError, match="not a regular file"):
        local_admin_token(TokenStore(data / "tokens.json"), data / "local_token")


def test_the_cli_reports_a_damaged_file_instead_of_a_traceback(tmp_path):
    (tmp_path / "local_token").write_text("garbage\n")
    done = subprocess.run([sys.executable, "-m", "server", "--data-dir", str(tmp_path),
                           "--port", "0", "--demo-avatar", "none"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "TELESPLAT_WARMUP": "false",
                               "TELESPLAT_STARTUP_ROOM": "false"})
    assert done.returncode == 2
    assert "error:" in done.stderr and "--rotate-local-token" in done.stderr
    assert "Traceback" not in done.stderr
