"""The rulings and the engineering records share one sequence of numbers, and every "decision N" the
code and the docs cite is in one of the two files, once."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def numbers(name: str) -> list[int]:
    text = (ROOT / "docs" / name).read_text(encoding="utf-8")
    return [int(n) for n in re.findall(r"^(\d+)\. \*\*", text, re.M)]


def test_every_number_is_in_exactly_one_of_the_two_files() -> None:
    rulings, records = numbers("decisions.md"), numbers("engineering.md")
    both = rulings + records
    assert len(both) == len(set(both)), "a number is used twice"
    assert sorted(both) == list(range(1, max(both) + 1)), "the numbers have a gap"
    assert rulings == sorted(rulings) and records == sorted(records)


def test_every_cited_decision_exists() -> None:
    known = set(numbers("decisions.md")) | set(numbers("engineering.md"))
    cited: dict[int, str] = {}
    files = [*(ROOT / "src").rglob("*.py"), *(ROOT / "docs").glob("*.md"), ROOT / "README.md"]
    for path in files:
        text = path.read_text(encoding="utf-8")
        for match in re.finditer(r"\bdecisions? (\d+)(?:(?:, | and | or )(\d+))*", text):
            for number in re.findall(r"\d+", match.group(0)):
                cited.setdefault(int(number), str(path.relative_to(ROOT)))
    missing = {n: where for n, where in cited.items() if n not in known}
    assert missing == {}, f"cited but recorded nowhere: {missing}"
