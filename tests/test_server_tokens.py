"""The token store shared between processes (reload, locked writes) and log redaction."""

from __future__ import annotations

import json
import logging
import threading

from server.auth import Principal, TokenStore
from server.logsafe import install_log_redaction, redact


def test_another_writers_tokens_and_revocations_are_seen(tmp_path):
    path = tmp_path / "tokens.json"
    server = TokenStore(path, reload_interval_s=0.0)
    mine = server.issue("local", ["admin"])
    cli = TokenStore(path)  # e.g. `telesplat serve --issue-token` in another process
    theirs = cli.issue("carol", ["stream"])
    assert server.principal(theirs) == Principal("carol", frozenset({"stream"}))
    assert server.principal(mine) is not None  # the other writer kept it
    assert cli.revoke(theirs)
    assert server.principal(theirs) is None


def test_a_broken_file_keeps_the_tokens_loaded_before(tmp_path, caplog):
    path = tmp_path / "tokens.json"
    store = TokenStore(path, reload_interval_s=0.0)
    token = store.issue("ann", ["stream"])
    path.write_text('{"tokens": [{"no": "hash"')  # a hand edit gone wrong
    with caplog.at_level(logging.WARNING, logger="server.auth"):
        assert store.principal(token) is not None
    assert "unreadable" in caplog.text
    path.write_text(json.dumps({"tokens": []}))  # fixed: now it counts
    assert store.principal(token) is None


def test_concurrent_writers_lose_nothing(tmp_path):
    path = tmp_path / "tokens.json"
    stores = [TokenStore(path) for _ in range(4)]
    issued: list[str] = []

    def issue(store: TokenStore) -> None:
        for _ in range(10):
            issued.append(store.issue("many", ["stream"]))

    threads = [threading.Thread(target=issue, args=(s,)) for s in stores]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert len(issued) == 40
    fresh = TokenStore(path)
    assert all(fresh.principal(t) is not None for t in issued)
    assert oct(path.stat().st_mode & 0o777) == "0o600"


def test_redaction_patterns():
    line = ('127.0.0.1:1 - "GET /x?avatar=a&token=tsk_s3cr3t&ticket=tkt_abc#token=zz HTTP/1.1" '
            'Authorization: Bearer opaque-value, tsk_loose-one')
    out = redact(line)
    for secret in ("s3cr3t", "tkt_abc", "zz", "opaque-value", "loose-one"):
        assert secret not in out
    assert "avatar=a&token=[redacted]&ticket=[redacted]#token=[redacted]" in out
    assert redact("nothing to hide: tokens=3, tokenizer") == "nothing to hide: tokens=3, tokenizer"


def test_every_logger_redacts_once_installed(caplog):
    install_log_redaction()
    install_log_redaction()  # idempotent
    with caplog.at_level(logging.INFO):
        logging.getLogger("some.library").info("calling %s", "/v1/stream?token=tsk_abc")
        logging.getLogger("other").info({"dict": "args"})  # not a string: left alone
    assert "tsk_abc" not in caplog.text and "token=[redacted]" in caplog.text
