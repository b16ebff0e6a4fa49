"""The commands the README and docs show use options their commands have.

Every ``tactile-*`` command and ``python bench/*.py`` script in a shell block or an inline code
span of ``README.md``, ``docs/*.md`` and the folders' READMEs is parsed, and each ``--option``
it gives must be in that command's ``--help``: a renamed or removed option leaves no copy-paste
in the docs that ends in a usage error.
"""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
            *sorted(p for p in ROOT.glob("*/**/README.md")
                    if not {".venv", ".pytest_cache"} & set(p.parts))]


SHELL = ("", "sh", "bash", "console", "shell")


def shown(text: str):
    """Each command line of ``text``: the lines of its shell blocks (a trailing backslash
    joins the next line, comments dropped) and its inline code spans (in prose, where one may
    wrap onto the next line)."""
    prose, block, lang = [], None, ""
    for line in text.splitlines():
        fence = re.match(r"\s*```(\w*)", line)
        if fence and block is None:
            block, lang = [], fence.group(1)
        elif fence:
            if lang in SHELL:
                for command in re.sub(r"\\\n\s*", " ", "\n".join(block)).splitlines():
                    if not command.lstrip().startswith("#"):
                        yield command.split(" #")[0]
            block = None
        elif block is not None:
            block.append(line)
        else:
            prose.append(line)
    for span in re.findall(r"`([^`]+)`", "\n".join(prose)):
        if "\n\n" not in span:
            yield " ".join(span.split())


def invocations(line: str):
    """(command, its arguments) of each command of ``line`` that is a tactile command or a
    bench script; environment assignments before it are skipped."""
    for part in re.split(r"&&|\|\||;|\|", line):
        try:
            words = shlex.split(part)
        except ValueError:  # a span that is not a command (an unmatched quote)
            continue
        while words and re.match(r"[A-Z_][A-Z0-9_]*=", words[0]):
            words = words[1:]
        if words and re.fullmatch(r"tactile-[a-z-]+", words[0]):
            yield words[0], words[1:]
        elif words[:1] in (["python"], ["python3"]) and len(words) > 1 and re.fullmatch(
                r"bench/\w+\.py", words[1]):
            yield words[1], words[2:]


@functools.cache
def options(command: str) -> frozenset[str] | None:
    """The ``--options`` of ``command``'s help; None for a tactile-* name that is no command
    (a device's or a format's name in the docs)."""
    if command.startswith("tactile-"):
        if command not in SCRIPTS:
            return None
        module = SCRIPTS[command].split(":")[0]
        argv = [sys.executable, "-c", f"import sys; from {module} import main; "
                "sys.exit(main())", "--help"]
    else:
        argv = [sys.executable, str(ROOT / command), "--help"]
    run = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert run.returncode == 0, f"{command} --help: {run.stderr[-500:]}"
    return frozenset(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", run.stdout))


def test_every_option_the_docs_show_is_the_commands():
    wrong, checked = [], 0
    for path in doc_files():
        for line in shown(path.read_text()):
            for command, args in invocations(line):
                given = [a.split("=")[0] for a in args if a.startswith("--") and len(a) > 2]
                known = options(command)
                if known is None:
                    assert not given, f"{path.name}: {command} is not a command: {line}"
                    continue
                checked += 1
                wrong += [f"{path.relative_to(ROOT)}: {command} has no {o}: {line.strip()}"
                          for o in given if o not in known]
    assert not wrong, "\n".join(wrong)
    assert checked > 300, checked  # the parser found the docs' commands
