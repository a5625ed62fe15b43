"""A CLI run in the test's own process: ``main(argv)`` as ``python -m`` calls it, with its
exit status (argparse's SystemExit included) and what it printed. A subprocess per call costs
an interpreter and torch's import (tens of seconds on a busy 2-core CI); the ``python -m``
entries themselves run in tests/test_docs_commands.py and tests/test_cli.py."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Ran:
    returncode: int
    stdout: str
    stderr: str


def run_main(main: Callable[[list[str]], int], args, capsys) -> Ran:
    """``main(list(args))`` with pytest's ``capsys`` capturing its output."""
    capsys.readouterr()  # only this run's output
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's errors and --help, as `python -m` would exit
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    out = capsys.readouterr()
    return Ran(code, out.out, out.err)
