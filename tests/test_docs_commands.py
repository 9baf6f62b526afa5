"""Every ``scenesig ...`` command printed in README.md and docs/*.md names a real subcommand and real flags.

Commands are taken from shell code blocks (lines starting with ``scenesig``, also after ``&&``, ``;``,
``do`` or ``$``, with their indented continuation lines) and from inline code spans; the rows of a table
whose header is a ``scenesig X …`` span are that command's.  Each is checked against the real parser
(:func:`scenesig.cli.build_parser`, nothing executed): every subcommand word must exist, every ``--flag``
must be an option of the subcommand (for ``bench NAME`` and ``aerial bench``, which hand their arguments to
the benchmark, an option in the benchmark's own ``--help``), and a line without placeholders must parse.
So renaming a command or a flag fails here until the docs follow.  Which documented commands are also
*run* by a test is listed in docs/checks.md.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import re
import shlex
from functools import lru_cache
from pathlib import Path

import pytest

from scenesig.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

_FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
_SPAN = re.compile(r"`(scenesig [a-z][^`]*)`")
_FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
_START = re.compile(r"(?:^|&&\s*|;\s*|\bdo\s+|\$\s+)(scenesig\s+[a-z].*?)(?=\s*(?:&&|;|\bdone\b|$))")
_PLACEHOLDER = re.compile(r"[\[\]{}|…<>$]|\.\.\.|\b[A-Z][A-Z0-9_]{1,}\b")


def _commands(path: Path) -> list[tuple[str, str, bool]]:
    """``(where, command, runnable)`` for every command printed in ``path``: ``runnable`` for a code block's
    line (an invocation), not for a span in prose (which may name a command without its arguments)."""
    text = path.read_text(encoding="utf-8")
    found = []
    for m in _FENCE.finditer(text):
        if m.group(1) not in ("", "bash", "sh", "console", "shell"):
            continue
        line_no = text.count("\n", 0, m.start()) + 2
        lines = re.sub(r"\\\n\s*", " ", m.group(2)).splitlines()     # shell line continuations
        for i, line in enumerate(lines):
            body = line.split("  #", 1)[0]
            # a wrapped synopsis: indented lines after a command line belong to it
            j = i + 1
            while j < len(lines) and lines[j].startswith((" ", "\t")) and lines[j].strip() and _START.search(line):
                body += " " + lines[j].split("  #", 1)[0].strip()
                j += 1
            for c in _START.finditer(body):
                found.append((f"{path.name}:{line_no + i}", c.group(1), True))
    prose = _FENCE.sub("", text)
    for m in _SPAN.finditer(prose):
        found.append((f"{path.name}:{text.count(chr(10), 0, text.find(m.group(0))) + 1}",
                      " ".join(m.group(1).split()), False))
    # tables headed by a command: each row's first code span is an invocation of it
    for m in re.finditer(r"^\| `(scenesig [a-z][^`]*?)\s*…?` \|.*\n\|[-| ]+\|\n((?:\|.*\n)+)", text, re.M):
        prefix = m.group(1).rstrip(" …")
        for row in m.group(2).splitlines():
            cell = re.match(r"\| `([^`]+)`", row)
            if cell:
                found.append((f"{path.name} table", f"{prefix} {cell.group(1)}", False))
    return found


def _tokens(command: str) -> list[str]:
    try:
        return shlex.split(command)
    except ValueError:
        return command.split()


def _subparsers(parser: argparse.ArgumentParser):
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


@lru_cache(maxsize=None)
def _benchmark_help(module: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        with pytest.raises(SystemExit):
            importlib.import_module(f"scenesig.benchmarks.{module}").main(["--help"])
    return out.getvalue()


def _check(command: str, runnable: bool = True) -> str | None:
    """None when ``command`` agrees with the parser, else what is wrong (``runnable``: it must parse whole
    unless it has placeholders; else it may stop at a command's name)."""
    tokens = _tokens(command)
    parser, path, i = build_parser(), ["scenesig"], 1
    while (sub := _subparsers(parser)) is not None:
        word = tokens[i] if i < len(tokens) else None
        if word is None or word.startswith("-"):
            if word in ("-h", "--help") or (word is None and not runnable):
                return None
            return f"'{' '.join(path)}' needs a subcommand"
        names = word.split("|")
        if all(n in sub.choices for n in names):     # `export kapture|rosbag`: each alternative exists
            parser, path, i = sub.choices[names[0]], path + [names[0]], i + 1
            continue
        if _PLACEHOLDER.search(word):    # `scenesig bench NAME --help`
            return None
        return f"'{' '.join(path)}' has no subcommand {word!r} (choices: {', '.join(sorted(sub.choices))})"
    options = set(parser._option_string_actions)
    passes_on = parser.get_default("_pass_extra")
    if passes_on:
        module = parser.get_default("_bench") or "aerial"
        options |= set(_FLAG.findall(_benchmark_help(module))) | {"--help", "-h"}
    rest = " ".join(tokens[i:])
    unknown = sorted({f for f in _FLAG.findall(rest) if f not in options})
    if unknown:
        return f"'{' '.join(path)}' has no option {', '.join(unknown)}"
    if runnable and not _PLACEHOLDER.search(command) and not passes_on and "--help" not in tokens:
        try:
            with contextlib.redirect_stderr(io.StringIO()) as err:
                build_parser().parse_args(tokens[1:])
        except SystemExit:
            return f"does not parse: {err.getvalue().strip().splitlines()[-1:]}"
    return None


ALL = [c for doc in DOCS for c in _commands(doc)]


def test_the_docs_print_commands():
    """The extraction finds the README's own commands (so the check below cannot pass on nothing)."""
    readme = {cmd for where, cmd, runnable in ALL if where.startswith("README.md") and runnable}
    assert "scenesig demo" in readme, sorted(readme)
    assert sum(runnable for *_, runnable in ALL) > 40 and len(ALL) > 100, len(ALL)


@pytest.mark.parametrize("where,command,runnable", ALL, ids=[f"{w} {c[:60]}" for w, c, _ in ALL])
def test_documented_command_matches_the_parser(where, command, runnable):
    problem = _check(command, runnable)
    assert problem is None, f"{where}: `{command}`: {problem}"


@pytest.mark.parametrize("command,problem", [
    ("scenesig localise MAP RUN --out DIR --methd orb", "no option --methd"),
    ("scenesig build-mapp RUN --out maps/x", "no subcommand"),
    ("scenesig map shoe maps/x", "no subcommand"),
    ("scenesig bench heading DATASET --no-such-flag", "no option --no-such-flag"),
    ("scenesig demo --preset huge", "does not parse"),
])
def test_a_renamed_command_or_flag_is_caught(command, problem):
    assert problem in (_check(command) or ""), _check(command)
