"""The one error enrollment raises for input it will not train on: before any training starts,
and with what the person should do differently."""

from __future__ import annotations


class EnrollmentRefused(Exception):
    """A video (or its frames) that cannot become an avatar.

    ``reason``: a short machine-readable cause (``no_person``, ``two_people``, ``too_short``,
    ``never_turns``, ``too_dark``, ``too_blurred``, ``corrupt_video``, ...);
    ``what_to_do``: one sentence for the person who recorded it."""

    def __init__(self, reason: str, message: str, what_to_do: str) -> None:
        super().__init__(f"{message} {what_to_do}".strip())
        self.reason = reason
        self.message = message
        self.what_to_do = what_to_do

    def to_dict(self) -> dict[str, str]:
        return {"reason": self.reason, "message": self.message, "what_to_do": self.what_to_do}
