"""Keep tokens out of every log line: ``?token=``/``?ticket=`` values and bearer tokens.

Installed as a log-record factory, so it covers every logger in the process (uvicorn's access
and error logs, ours, libraries') whatever handlers uvicorn's logging config sets up later.
Only string arguments are rewritten: uvicorn's access formatter unpacks ``record.args`` and
needs the others (the status code) as they are.
"""

from __future__ import annotations

import logging
import re
from typing import Any

REDACTED = "[redacted]"
_PATTERNS = (
    # token=..., ticket=..., access_token=... in a query string or a fragment
    (re.compile(r"(?i)\b((?:access_)?token|ticket)=[^&#\s\"']+"), rf"\1={REDACTED}"),
    (re.compile(r"(?i)\b(bearer\s+)[^\s\"',]+"), rf"\1{REDACTED}"),
    (re.compile(r"\btsk_[A-Za-z0-9_\-]+"), f"tsk_{REDACTED}"),  # our tokens, anywhere
)


_FORMATTER = logging.Formatter()


def redact(text: str) -> str:
    """``text`` with token values replaced by ``[redacted]``."""
    for pattern, replacement in _PATTERNS:
        text = pattern.sub(replacement, text)
    return text


def _redact_value(value: Any) -> Any:
    return redact(value) if isinstance(value, str) else value


def redact_record(record: logging.LogRecord) -> logging.LogRecord:
    """Redact a record's message and string arguments in place."""
    if isinstance(record.msg, str):
        record.msg = redact(record.msg)
    if isinstance(record.args, tuple):
        record.args = tuple(_redact_value(a) for a in record.args)
    elif isinstance(record.args, dict):
        record.args = {k: _redact_value(v) for k, v in record.args.items()}
    if record.exc_info and not record.exc_text:  # formatters reuse exc_text when it is set
        record.exc_text = redact(_FORMATTER.formatException(record.exc_info))
    return record


def install_log_redaction() -> None:
    """Wrap the log-record factory once per process; idempotent."""
    current = logging.getLogRecordFactory()
    if getattr(current, "redacts_tokens", False):
        return

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        return redact_record(current(*args, **kwargs))

    factory.redacts_tokens = True  # type: ignore[attr-defined]
    logging.setLogRecordFactory(factory)
