"""Every `gmt` command line in the README and docs/ names commands and flags that exist: each shell block's
`gmt SUB [SUBSUB] --flag ...` is checked against the command's own options (the click command `gmt` builds, so no
subprocess per line). Blocks too long for CI (training, full evaluations) are checked this way only; the short ones
whose printed output the docs show are run by tests/service/test_doc_outputs.py."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from gmt.service import cli

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SEPARATORS = {"|", "||", "&&", ";", "&"}


def shell_lines(text: str) -> list[str]:
    """The logical lines of every ```bash block (continuations joined)."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        out += [line for line in block.replace("\\\n", " ").splitlines() if line.strip()]
    return out


def invocations(line: str) -> list[list[str]]:
    """The argument lists after each `gmt` (or `.venv/bin/gmt`) on a shell line, up to a separator."""
    try:
        tokens = shlex.split(line, comments=True)
    except ValueError:  # an unbalanced quote inside $(...): split plainly, up to a comment
        tokens = line.split(" #")[0].split()
    found, current = [], None
    for t in tokens:
        if t in SEPARATORS or t.endswith(";"):
            current = None
        elif current is not None:
            current.append(t)
        elif t == "gmt" or t.endswith("/gmt"):
            current = []
            found.append(current)
    return found


def options(command) -> set[str]:
    return {o for p in command.params for o in (*p.opts, *p.secondary_opts)} | {"--help"}


COMMANDS = {e.name: e for e in cli.COMMANDS}


def check(args: list[str]) -> str | None:
    """Why `gmt ARGS` would not parse (an unknown command or flag), or None."""
    if not args or args[0] in ("--help", "version", "--version"):
        return None
    entry = COMMANDS.get(args[0])
    if entry is None:
        return f"no command gmt {args[0]}"
    command, rest = entry.load(), args[1:]
    if hasattr(command, "commands"):  # a group (typer's click may not be the `click` imported here)
        if not rest or rest[0].startswith("-"):
            return None  # `gmt models --help` and the like
        sub = command.commands.get(rest[0])
        if sub is None:
            return f"no command gmt {args[0]} {rest[0]}"
        command, rest = sub, rest[1:]
    known = options(command)
    for t in rest:
        if t == "--":
            break  # what follows goes to another program (gmt cluster up -- <gmt serve flags>)
        if t.startswith("--") and t.split("=")[0] not in known:
            return f"gmt {' '.join(args[: len(args) - len(rest)])}: no option {t.split('=')[0]}"
    return None


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_documented_gmt_line_names_existing_commands_and_flags(doc):
    problems = []
    for line in shell_lines(doc.read_text()):
        for args in invocations(line):
            why = check(args)
            if why is not None:
                problems.append(f"{why}\n    in: {line.strip()}")
    assert not problems, f"{doc.name}:\n" + "\n".join(problems)


def test_a_wrong_flag_is_caught():
    assert check(["run", "--no-such-flag"]) == "gmt run: no option --no-such-flag"
    assert check(["models", "promote", "m", "v", "--share", "0.1"]) is None
    assert check(["models", "nope"]) == "no command gmt models nope"
    assert invocations("S=$(x) && .venv/bin/gmt run --steps 5 | tee a  # gmt fake --x") == [
        ["run", "--steps", "5"]
    ]
