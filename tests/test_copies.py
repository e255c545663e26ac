"""The method scripts repeat code on purpose (one self-contained file per method); the copies must not drift.

Each script is split at its section banners (a line of dashes, a title line "# Name: ...", a line of dashes).
SHARED declares, in this one place, which sections are byte-identical across which scripts: a fix made in one
copy and not in the others fails here, naming the section and the script that drifted."""

from __future__ import annotations

import os
import re
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BANNER = "# " + "-" * 93
ALL = ("claw", "dr", "st", "oracle", "film", "concat", "posthoc")
# section name -> groups of scripts whose copies of it are identical (the first script of a group is the reference)
SHARED = {
    "Math": [ALL],
    "Networks": [("claw", "dr", "st", "oracle", "posthoc")],
    "LoRA": [("claw", "dr", "st", "oracle", "posthoc")],
    "Hypernetwork": [("claw", "film", "posthoc")],
    "MPPI planner": [ALL],
    "Buffers": [("claw", "film", "concat", "posthoc"), ("dr", "st", "oracle")],
    "Update": [("claw", "film"), ("dr", "st", "oracle")],
    "Evaluation": [("claw", "film"), ("dr", "st")],
    "Argument checks": [("claw", "film", "concat"), ("dr", "oracle")],
    "Run plumbing": [ALL],
    "Persistence": [("claw", "film", "concat"), ("dr", "st", "oracle")],
}
# every script's sections, in this order: the method before the plumbing
ORDER = (
    "Math",
    "Networks",
    "*",
    "MPPI planner",
    "Buffers",
    "Update",
    "Evaluation",
    "Main",
    "Argument checks",
    "Run plumbing",
    "Persistence",
)


def script_text(script: str) -> str:
    with open(os.path.join(REPO, f"{script}_tdmpc2.py")) as f:
        return f.read()


def sections(script: str) -> dict[str, str]:
    """Section name (the banner title up to its first ':' or '(') -> the section's text; "head" is what precedes the
    first banner (docstring, imports, the paper's tables, Args)."""
    lines = script_text(script).split("\n")
    found, name, start = {}, "head", 0
    for i in range(len(lines) - 2):
        if lines[i] == BANNER and lines[i + 2] == BANNER and lines[i + 1].startswith("# "):
            found[name] = "\n".join(lines[start:i])
            name, start = re.split(r"[:(]", lines[i + 1][2:])[0].strip(), i + 3
    found[name] = "\n".join(lines[start:])
    return found


@pytest.mark.parametrize("section", sorted(SHARED))
def test_shared_sections_are_identical(section):
    for group in SHARED[section]:
        reference = sections(group[0])
        assert section in reference, f"{group[0]}_tdmpc2.py has no section {section!r}"
        for script in group[1:]:
            copy = sections(script)
            assert section in copy, f"{script}_tdmpc2.py has no section {section!r}"
            assert copy[section] == reference[section], (
                f"section {section!r} of {script}_tdmpc2.py drifted from {group[0]}_tdmpc2.py's: make the same change in every "
                f"script of {', '.join(group)}"
            )


@pytest.mark.parametrize("script", ALL)
def test_sections_in_order_method_before_plumbing(script):
    names = [n for n in sections(script) if n != "head"]
    fixed = [n for n in names if n in ORDER]
    assert fixed == [n for n in ORDER if n in fixed], f"{script}_tdmpc2.py: sections out of order: {names}"
    assert names.index("Networks") < names.index("MPPI planner"), names
    assert all(names.index("Networks") < names.index(n) < names.index("MPPI planner") for n in names if n not in ORDER), (
        f"{script}_tdmpc2.py: the method's own sections belong between Networks and the planner: {names}"
    )
    assert script_text(script).rstrip().endswith("main(tyro.cli(Args), typed=typed_flags(sys.argv[1:]))"), (
        "the script ends with its entry point"
    )


def test_a_drifted_copy_is_named(monkeypatch):
    """The guard itself: a one-character change in one script's copy is reported with that script's name."""
    original = script_text
    drifted = original("st").replace("def symlog(x):", "def symlog(x):  # changed", 1)
    monkeypatch.setattr(sys.modules[__name__], "script_text", lambda script: drifted if script == "st" else original(script))
    with pytest.raises(AssertionError, match="'Math' of st_tdmpc2.py drifted"):
        test_shared_sections_are_identical("Math")
