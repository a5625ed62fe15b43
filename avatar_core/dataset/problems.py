"""What validation finds: problems with a code, a severity and an exact location."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

__all__ = ["ERROR", "WARNING", "DatasetError", "Problem", "Where", "errors_of", "problem"]

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Where:
    """Where a problem lies; unset fields do not apply. `frames` lists every affected frame
    (one for a file, several for a parameter array); `path` is relative to the dataset root."""

    sequence: str | None = None
    camera: str | None = None
    frames: tuple[int, ...] = ()
    key: str | None = None
    path: str | None = None

    @property
    def frame(self) -> int | None:
        """The frame when exactly one is affected."""
        return self.frames[0] if len(self.frames) == 1 else None

    def __str__(self) -> str:
        parts = []
        if self.sequence is not None:
            parts.append(f"sequence={self.sequence}")
        if self.camera is not None:
            parts.append(f"camera={self.camera}")
        if self.frames:
            parts.append(f"frame{'s' if len(self.frames) > 1 else ''}={_ranges(self.frames)}")
        if self.key is not None:
            parts.append(f"key={self.key}")
        if self.path is not None:
            parts.append(f"path={self.path}")
        return " ".join(parts) or "dataset"


def _ranges(frames: Iterable[int]) -> str:
    """(0, 1, 2, 5) -> '0-2,5' (long frame lists stay readable)."""
    out: list[str] = []
    run: list[int] = []
    for f in sorted(frames):
        if run and f == run[-1] + 1:
            run.append(f)
            continue
        if run:
            out.append(str(run[0]) if len(run) == 1 else f"{run[0]}-{run[-1]}")
        run = [f]
    if run:
        out.append(str(run[0]) if len(run) == 1 else f"{run[0]}-{run[-1]}")
    return ",".join(out)


@dataclass(frozen=True)
class Problem:
    code: str        # stable identifier, listed in docs/dataset.md
    where: Where
    message: str
    severity: str = ERROR

    def __str__(self) -> str:
        return f"{self.severity}: {self.code} at {self.where}: {self.message}"


def problem(code: str, message: str, severity: str = ERROR, **where: Any) -> Problem:
    """Shorthand: problem("missing_image", "...", sequence="s", camera="c", frames=(3,))."""
    return Problem(code, Where(**where), message, severity)


def errors_of(problems: Iterable[Problem]) -> list[Problem]:
    return [p for p in problems if p.severity == ERROR]


class DatasetError(ValueError):
    """A dataset (or a dataset being written) has errors; `problems` lists all of them."""

    def __init__(self, root: object, problems: list[Problem]) -> None:
        self.problems = list(problems)
        lines = "\n".join(f"  {p}" for p in self.problems)
        super().__init__(f"dataset {root} has {len(self.problems)} problem(s):\n{lines}")
