"""The documentation keeps its promises: the README stays short and opens with CI's two
commands, the configuration reference is the generated one, and no relative link is broken."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from app.tools.configdoc import COMMAND, render

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

SIMULATE = ("python3 -m venv .venv && .venv/bin/pip install -q . && "
            ".venv/bin/midair simulate --out out/simulate")
PYTEST = ("python3 -m venv .venv && .venv/bin/pip install -q -e '.[dev]' && "
          ".venv/bin/python -m pytest")

FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
CODE_SPAN = re.compile(r"`[^`\n]*`")


def documents() -> list[Path]:
    return [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]


def fenced_commands(text: str) -> list[str]:
    """The command lines of the fenced code blocks, in order (comments and blanks left out)."""
    lines: list[str] = []
    for block in FENCE.findall(text):
        lines.extend(line.strip() for line in block.splitlines()
                     if line.strip() and not line.strip().startswith("#"))
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = CODE_SPAN.sub(lambda m: m.group(0)[1:-1], heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.MULTILINE):
        base = slug(heading)
        name, n = base, 0
        while name in found:
            n += 1
            name = f"{base}-{n}"
        found.add(name)
    return found


def test_configuration_reference_is_generated() -> None:
    committed = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert committed == render(), f"docs/configuration.md is out of date: regenerate it with `{COMMAND}`"


def test_readme_is_short() -> None:
    lines = README.read_text(encoding="utf-8").count("\n")
    assert lines <= 250, f"README.md has {lines} lines (at most 250): move detail to docs/"


def test_readme_opens_with_the_two_ci_commands() -> None:
    commands = fenced_commands(README.read_text(encoding="utf-8"))
    assert commands[:2] == [SIMULATE, PYTEST], (
        "the README's first two fenced commands are CI's contract: setup + simulate, setup + pytest")


def test_ci_runs_the_readme_test_command() -> None:
    assert PYTEST in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()


@pytest.mark.parametrize("doc", documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc: Path) -> None:
    if not doc.exists():
        pytest.skip(f"{doc.name} absent")
    text = FENCE.sub("", doc.read_text(encoding="utf-8"))
    broken: list[str] = []
    for target in LINK.findall(CODE_SPAN.sub("", text)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):
            continue  # https:, mailto: ...
        path_part, _, fragment = target.partition("#")
        path = (doc.parent / path_part).resolve() if path_part else doc
        if not path.exists():
            broken.append(f"{target} (no such file)")
        elif fragment and path.suffix == ".md" and fragment not in anchors(path):
            broken.append(f"{target} (no heading #{fragment} in {path.name})")
    assert not broken, f"{doc.relative_to(ROOT)}: broken links: {', '.join(broken)}"
