"""Docs that stay true: every ``telesplat`` / ``telesplat-client`` command line in README.md
and docs/*.md (inside ```sh blocks, and unlabelled blocks) names commands, options and values
that exist.

Each line is read against the real argparse trees (``avatar_core.cli.build_parser`` with its
plugins, ``client.cli.build_parser``): the subcommand path must exist, every option used must
exist on that subcommand, and a concrete value of an option with choices, of ``--motion``
(built-in clips), ``--camera`` / ``--view`` (camera presets) and ``--config`` (training
presets) must be a known one. Synopsis lines are understood: ``[...]`` optional parts, ``a|b``
alternatives, `` | `` between sibling subcommands, UPPER-CASE placeholders, files. Then every
distinct subcommand path runs with ``--help`` appended (all in one subprocess) and must exit 0.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from avatar_core.cli import _expand_shorthands
from avatar_core.cli import build_parser as engine_parser
from avatar_core.motion.library import clip_names
from avatar_core.train.config import PRESETS
from client.cli import build_parser as client_parser
from protocol.cameras import CAMERA_NAMES

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PROGRAMS = {"telesplat": ("avatar_core.cli", engine_parser),
            "telesplat-client": ("client.cli", client_parser)}
BLOCK_LANGS = ("sh", "bash", "shell", "console", "")
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_:.,/-]*$")  # ID, FILE.zip, DIR, HEAD:6379


@dataclass(frozen=True)
class DocLine:
    where: str   # file:line
    text: str


def doc_lines(paths: list[Path] = DOCS) -> list[DocLine]:
    """The command lines in fenced blocks, continuation lines joined."""
    out = []
    for path in paths:
        lines = path.read_text().splitlines()
        fence: str | None = None
        i = 0
        while i < len(lines):  # bounded: i grows every turn
            line = lines[i]
            m = re.match(r"\s*```\s*([\w-]*)", line)
            if m:
                fence = None if fence is not None else m.group(1)
                i += 1
                continue
            text = line.strip().removeprefix("$ ")
            start = i
            if fence is not None and fence in BLOCK_LANGS and re.match(
                    r"(telesplat|telesplat-client) ", text):
                while text.endswith("\\") and i + 1 < len(lines):
                    i += 1
                    text = text[:-1] + " " + lines[i].strip()
                name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
                out.append(DocLine(f"{name}:{start + 1}", text))
            i += 1
    return out


def _concrete(value: str) -> bool:
    """A value the docs name literally (not a placeholder, a file, a number or a list)."""
    return bool(re.fullmatch(r"[a-z][a-z0-9_-]*", value))


def _known_values(program: str, path: tuple[str, ...], action: argparse.Action
                  ) -> tuple[str, ...] | None:
    dest = action.dest
    if action.choices is not None and not isinstance(action.choices, dict):
        return tuple(str(c) for c in action.choices)
    if dest == "motion":
        return clip_names()
    if (program, dest) in (("telesplat", "camera"), ("telesplat-client", "view")):
        return CAMERA_NAMES if path == ("render",) or dest == "view" else None
    if program == "telesplat-client" and dest == "config":
        return tuple(PRESETS)
    return None


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


@dataclass
class Checked:
    problems: list[str] = field(default_factory=list)
    paths: set[tuple[str, tuple[str, ...]]] = field(default_factory=set)


def check_line(line: DocLine, parsers: dict[str, argparse.ArgumentParser],
               checked: Checked) -> None:
    try:
        tokens = shlex.split(line.text, comments=True)
    except ValueError as exc:
        checked.problems.append(f"{line.where}: cannot split {line.text!r}: {exc}")
        return
    program, tokens = tokens[0], [t.replace("[", "").replace("]", "") for t in tokens[1:]]
    tokens = [t for t in tokens if t not in ("", "...")]
    if program == "telesplat":
        tokens = _expand_shorthands(tokens)
    root = parsers[program]

    def problem(message: str) -> None:
        checked.problems.append(f"{line.where}: {message}\n    {line.text}")

    # descend the subcommand tree; `` | `` may switch to a sibling subcommand
    stack: list[tuple[str, argparse.ArgumentParser]] = [("", root)]
    leaves = []
    i = 0
    while i < len(tokens):  # bounded: i grows every turn
        token = tokens[i]
        current = stack[-1][1]
        subs = _subparsers(current)
        if token == "|":
            nxt = tokens[i + 1] if i + 1 < len(tokens) else ""
            parent_subs = _subparsers(stack[-2][1]) if len(stack) > 1 else {}
            if nxt in parent_subs and nxt not in subs:
                leaves.append(tuple(name for name, _ in stack[1:]))
                stack[-1] = (nxt, parent_subs[nxt])
                i += 2
                continue
            i += 1
            continue
        if subs and not token.startswith("-"):
            if token not in subs:
                problem(f"unknown command {token!r} after "
                        f"{' '.join([program, *(n for n, _ in stack[1:])])}; "
                        f"known: {', '.join(subs)}")
                return
            stack.append((token, subs[token]))
            i += 1
            continue
        for piece in token.split("|"):
            if not piece.startswith("-") or piece in ("-", "--") or re.match(r"-\d", piece):
                continue
            name, eq, inline = piece.partition("=")
            action = current._option_string_actions.get(name)
            path = tuple(n for n, _ in stack[1:])
            if action is None:
                problem(f"{' '.join([program, *path])} has no option {name}")
                continue
            value = inline if eq else (tokens[i + 1] if i + 1 < len(tokens) else "")
            if action.nargs == 0 or not value or value.startswith("-") or value == "|":
                continue
            known = _known_values(program, path, action)
            if known is None:
                continue
            for alternative in value.split("|"):
                if _concrete(alternative) and alternative not in known \
                        and not PLACEHOLDER.match(alternative):
                    problem(f"{' '.join([program, *path])} {name}: {alternative!r} is not "
                            f"one of {', '.join(known)}")
        i += 1
    leaves.append(tuple(name for name, _ in stack[1:]))
    for leaf in leaves:
        node = root
        for name in leaf:
            node = _subparsers(node)[name]
        if _subparsers(node):
            problem(f"{' '.join([program, *leaf])} needs a subcommand: "
                    f"{', '.join(_subparsers(node))}")
        checked.paths.add((program, leaf))


def check_docs(lines: list[DocLine]) -> Checked:
    parsers = {name: make() for name, (_, make) in PROGRAMS.items()}
    checked = Checked()
    for line in lines:
        check_line(line, parsers, checked)
    return checked


def test_the_docs_have_command_lines():
    lines = doc_lines()
    assert len(lines) >= 40
    assert any(line.text.startswith("telesplat dataset zip") for line in lines)


def test_every_doc_command_line_names_known_commands_options_and_values():
    checked = check_docs(doc_lines())
    assert not checked.problems, "\n".join(checked.problems)


def test_the_checker_catches_drift(tmp_path):
    bad = tmp_path / "bad.md"
    bad.write_text("\n".join([
        "```sh",
        "telesplat-client jobs submit --archive a.zip --config fastest --watch",
        "telesplat render AVATAR --motion smiel --camera back --out DIR",
        "telesplat-client rooms create --avatars demo",
        "telesplat-client rooms shout ROOM",
        "telesplat eval A D --protocol novel_view",
        "telesplat dataset",
        "```",
        "```sh",
        "telesplat render AVATAR --motion smile|talk_calm|FILE --camera front|orbit|FILE",
        "telesplat-client jobs list | status ID | watch ID",
        "```"]))
    problems = check_docs(doc_lines([bad])).problems
    text = "\n".join(problems)
    for expected in ("'fastest' is not one of", "'smiel' is not one of",
                     "'back' is not one of", "has no option --avatars",
                     "unknown command 'shout'", "'novel_view' is not one of",
                     "telesplat dataset needs a subcommand"):
        assert expected in text, text
    assert len(problems) == 7, text  # the last two lines are fine


# One interpreter for every path (a subprocess each cost seconds of imports on a busy CI): it
# runs each program's main with ``--help`` as ``python -m`` would, and reports exit code and
# output per path as JSON. The ``python -m`` entries run in test_help_names_every_preset_and_camera.
HELP_RUNNER = """
import contextlib, importlib, io, json, sys
out = []
for module, path in json.loads(sys.stdin.read()):
    main = importlib.import_module(module).main
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = main([*path, "--help"])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except Exception as exc:  # that path's failure, reported with the others
            print(repr(exc), file=sys.stderr)
            code = 1
    out.append([code, stdout.getvalue(), stderr.getvalue()])
print(json.dumps(out))
"""


def test_every_documented_command_runs_with_help():
    paths = sorted(check_docs(doc_lines()).paths)
    assert len(paths) >= 20
    asked = [(PROGRAMS[program][0], list(path)) for program, path in paths]
    done = subprocess.run([sys.executable, "-c", HELP_RUNNER], input=json.dumps(asked),
                          capture_output=True, text=True, timeout=300, cwd=ROOT,
                          env=dict(os.environ), check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    failures = []
    for (program, path), (code, stdout, stderr) in zip(paths, json.loads(done.stdout),
                                                        strict=True):
        if code != 0 or "usage:" not in stdout:
            failures.append(f"{program} {' '.join(path)} --help: rc {code}\n{stderr[-2000:]}")
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("program", list(PROGRAMS))
def test_help_names_every_preset_and_camera(program):
    module = PROGRAMS[program][0]
    args = ["jobs", "submit"] if program == "telesplat-client" else ["render"]
    done = subprocess.run([sys.executable, "-m", module, *args, "--help"], capture_output=True,
                          text=True, timeout=120, cwd=ROOT, env=dict(os.environ), check=False)
    assert done.returncode == 0, done.stderr
    help_text = " ".join(done.stdout.split())
    names = PRESETS if program == "telesplat-client" else CAMERA_NAMES
    for name in names:
        assert name in help_text, (name, help_text)
