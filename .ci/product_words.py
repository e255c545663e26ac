"""The product speaks of the software only: no narration of how the work was carried out (working periods and their
ordinals, issue numbers, lost machines, launcher logs, one machine's sweep paths) in code, tests or docs.
Prints each offending line and exits 1; run by .ci/run."""

import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
CHECKED = ["*.py", "*.md", "*.sh", "*.toml", "*.txt", "*.bib", "LICENSE", ".ci/run"]
SKIPPED = {".venv", "venv", "runs", ".git", "wandb"}
GENERATED = "results"  # tables written by experiments/aggregate.py from run metadata
ORDINALS = (
    r"(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|\w+teenth|twent\w*|thirt\w*|fort\w*|\d+(st|nd|rd|th))"
)
PATTERNS = [
    re.compile(r"\bsessions?\b(?!['\"]?\))", re.I),  # a working period (pytest's scope="session" is allowed below)
    re.compile(rf"\b{ORDINALS}[- ](session|period|stop)\b", re.I),
    re.compile(r"\b(issue|ticket)\s*#?\d+", re.I),
    re.compile(r"\blauncher_?\w*\d+\.log\b"),
    re.compile(r"/work/(sweeps|sweep_tree|main)\b"),
    re.compile(r"\b(lost|gone) (its |the |a )?machines?\b|\bmachines? (was|were) lost\b", re.I),
]
ALLOWED = re.compile(r"""scope=["']session["']|pytest""")


def offending_lines():
    for pattern in CHECKED:
        for path in sorted(ROOT.rglob(pattern)):
            parts = path.relative_to(ROOT).parts
            if SKIPPED & set(parts) or parts[0] == GENERATED or path.name == "product_words.py":
                continue
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                if not ALLOWED.search(line) and any(p.search(line) for p in PATTERNS):
                    yield f"{path.relative_to(ROOT)}:{number}: {line.strip()[:160]}"


if __name__ == "__main__":
    found = list(offending_lines())
    print("\n".join(found) if found else "product words: clean")
    sys.exit(1 if found else 0)
