"""Display names: what presence shows for a participant, chosen by the client.

A name is shown to everyone in a room, so it is bounded (``limits.max_name_chars``) and kept to
a plain charset: letters and digits of any script, spaces and ``. _ ' -``. Runs of spaces are
collapsed and the ends trimmed before checking; control, format and markup characters never
pass (the page shows names as text, but other clients might not).
"""

from __future__ import annotations

import re

NAME_PUNCTUATION = " ._'-"
_ALLOWED = re.compile(r"[\w .'-]+")  # \w: letters and digits of any script, and "_"


def display_name(text: str, max_chars: int) -> str:
    """``text`` as a display name, or ValueError saying what is wrong with it."""
    if not isinstance(text, str):
        raise ValueError("a name is a string")
    name = " ".join(text.split())
    if not name:
        raise ValueError("a name must not be empty")
    if len(name) > max_chars:
        raise ValueError(f"a name of {len(name)} characters exceeds the limit {max_chars} "
                         "(limits.max_name_chars)")
    if not _ALLOWED.fullmatch(name):
        bad = sorted({c for c in name if not _ALLOWED.fullmatch(c)})
        raise ValueError(f"a name may hold letters, digits, spaces and {NAME_PUNCTUATION[1:]!r}"
                         f" only, not {''.join(bad)!r}")
    return name
