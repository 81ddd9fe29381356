"""docs/companions.md's worked example is true: every line of each excerpt that names its file (a
first line ``# path`` or ``// path``) is a line of that file, in the same order."""

from __future__ import annotations

import re

from conftest import ROOT

DOC = ROOT / "docs" / "companions.md"


def excerpts() -> list[tuple[str, list[str]]]:
    found = []
    for block in re.findall(r"```(?:python|js)\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S):
        first, *lines = block.rstrip("\n").split("\n")
        named = re.fullmatch(r"(?:#|//) ((?:tests|src)/\S+)", first)
        if named:
            found.append((named.group(1), [line for line in lines if line.strip() != "..."]))
    return found


def test_each_excerpt_is_in_its_file_in_order() -> None:
    checked = excerpts()
    assert {path for path, _ in checked} == {
        "tests/companions/testco/companion.py",
        "tests/companions/testco/static/view.js",
        "tests/test_third_companion.py",
    }
    for path, lines in checked:
        text = (ROOT / path).read_text(encoding="utf-8").split("\n")
        at = 0
        for line in lines:
            assert line in text[at:], f"{path}: {line!r} is not there (after line {at})"
            at = text.index(line, at) + 1
