"""RESULTS.md states the paper's claims in the words of results/learn/runs/claims.md, so the two cannot drift.

claims.md (written by experiments/aggregate.py) has one line per claim, "- **<claim> (Exp k): <verdict>**", and under it
one line per comparison, "  - <what>: <difference> [<low>, <high>] (<n>): <verdict>", after a "  - by family: ..." line
where a claim spans families. Every claim line, family line and comparison line must appear verbatim in RESULTS.md, each claim with its verdict also in the "At a glance" section,
and the intervals and verdicts are checked one by one so that a failure names what differs. The figures and files
RESULTS.md links to must exist, its counts of archived runs must be the archive's, and RESULTS.md must stay under
25 KB. The tables in results/learn/runs are what experiments/aggregate.py writes from the archived runs there, byte
for byte."""

from __future__ import annotations

import csv
import os
import re

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARCHIVE = os.path.join(REPO, "results", "learn", "runs")
CLAIMS = os.path.join(ARCHIVE, "claims.md")
RESULTS = os.path.join(REPO, "RESULTS.md")
DETAILS = os.path.join(REPO, "docs", "results-details.md")

CLAIM = re.compile(r"^- \*\*(?P<claim>.+): (?P<verdict>[^:*]+)\*\*\s*$")
ROW = re.compile(r"^  - (?P<text>.+): (?P<verdict>supports|contradicts|not separable|runs missing.*)\s*$")
INTERVAL = re.compile(r"[+-]\d+(?:\.\d+)? \[[+-]\d+(?:\.\d+)?, [+-]\d+(?:\.\d+)?\]")


def read(path: str) -> str:
    with open(path, encoding="utf-8") as f:
        return f.read()


def parse_claims(text: str) -> list[dict]:
    """[{claim, verdict, line, by_family, rows: [{line, interval, verdict}]}] from claims.md's text."""
    claims: list[dict] = []
    for line in text.splitlines():
        if m := CLAIM.match(line):
            claims.append(
                {"claim": m["claim"], "verdict": m["verdict"], "line": line[2:].strip(), "rows": [], "by_family": None}
            )
        elif line.startswith("  - by family: ") and claims:
            claims[-1]["by_family"] = line.strip()[2:]
        elif (m := ROW.match(line)) and claims:
            found = INTERVAL.search(m["text"])
            claims[-1]["rows"].append(
                {"line": line.strip()[2:], "interval": found.group(0) if found else None, "verdict": m["verdict"]}
            )
    return claims


def glance(results: str) -> str:
    """The text of RESULTS.md's "At a glance" section."""
    start = results.index("## At a glance")
    end = results.find("\n## ", start + 1)
    return results[start : end if end != -1 else len(results)]


def missing(claims_text: str, results_text: str) -> list[str]:
    """What of claims.md does not appear verbatim in RESULTS.md (empty when the two agree)."""
    out = []
    summary = glance(results_text)
    for c in parse_claims(claims_text):
        if c["line"] not in results_text:
            out.append(f"claim line: {c['line']}")
        if c["by_family"] and c["by_family"] not in results_text:
            out.append(f"family line: {c['by_family']}")
        if f"**{c['claim']}: {c['verdict']}**" not in summary:
            out.append(f"claim not in 'At a glance' with its verdict: {c['claim']}: {c['verdict']}")
        for r in c["rows"]:
            if r["line"] not in results_text:
                out.append(f"comparison line: {r['line']}")
            if r["interval"] and f"{r['interval']}" not in results_text:
                out.append(f"interval: {r['interval']}")
    return out


@pytest.fixture(scope="module")
def texts() -> tuple[str, str]:
    return read(CLAIMS), read(RESULTS)


def test_claims_file_parses_into_six_claims_with_intervals(texts):
    claims = parse_claims(texts[0])
    assert len(claims) == 6, [c["claim"] for c in claims]
    rows = [r for c in claims for r in c["rows"]]
    assert len(rows) >= 6 and all(c["rows"] for c in claims)
    assert all(r["interval"] for r in rows if not r["verdict"].startswith("runs missing"))
    assert all(c["by_family"] for c in claims[:2])  # Exp 1 and 2 span the Exp 1/2 families


def test_results_quotes_every_claim_verdict_and_interval(texts):
    claims_text, results_text = texts
    assert missing(claims_text, results_text) == []


def test_check_fails_when_an_interval_or_verdict_drifts(texts):
    claims_text, results_text = texts
    claims = parse_claims(claims_text)
    row = next(r for c in claims for r in c["rows"] if r["interval"])
    # RESULTS.md with one interval changed by a digit: the check must name it
    changed = row["interval"].replace(row["interval"][-2], "9" if row["interval"][-2] != "9" else "8", 1)
    assert missing(claims_text, results_text.replace(row["interval"], changed))
    # claims.md with a verdict the RESULTS text does not state
    decided = next(c for c in claims if c["verdict"] != "runs missing")
    flipped = claims_text.replace(decided["line"], decided["line"].replace(decided["verdict"], "runs missing"))
    assert any("claim" in m for m in missing(flipped, results_text))
    # claims.md with a family verdict the RESULTS text does not state
    family = claims[0]["by_family"]
    assert any("family line" in m for m in missing(claims_text.replace(family, family + "; go1 reproduced"), results_text))


def test_linked_files_exist():
    for doc in (RESULTS, DETAILS):
        base = os.path.dirname(doc)
        for target in re.findall(r"\]\(([^)#\s]+)\)", read(doc)):
            if "://" in target:
                continue
            if target == "docs/sweeps.md":  # written alongside; linked before it lands
                continue
            assert os.path.exists(os.path.normpath(os.path.join(base, target))), f"{os.path.relpath(doc, REPO)}: {target}"


def test_results_is_at_most_25_kb():
    assert os.path.getsize(RESULTS) <= 25 * 1024


def test_results_counts_are_the_archives():
    """The run, resume and weight counts RESULTS.md gives are those of the archived runs' folders."""
    import json

    runs = sorted(n for n in os.listdir(ARCHIVE) if os.path.isfile(os.path.join(ARCHIVE, n, "run.json")))
    resumed = sum(json.loads(read(os.path.join(ARCHIVE, n, "run.json"))).get("resumed") is True for n in runs)
    training = [n for n in runs if not n.startswith("controls")]  # the controls only evaluate a checkpoint
    weighed = sum(os.path.isfile(os.path.join(ARCHIVE, n, "checkpoint.pt")) for n in training)
    text = " ".join(read(RESULTS).split())  # line breaks as spaces
    assert f"the {len(runs)} runs archived" in text
    assert f"in {resumed} of the {len(runs)} `run.json`" in text
    assert f"{weighed} of the {len(training)} training runs keep their weights" in text


# what experiments/aggregate.py writes from an archive, all committed beside its runs
TABLES = ("summary.md", "claims.md", "controls.md", "training_curves.md")
CSVS = ("summary.csv", "curves.csv", "controls.csv", "training_curves.csv")


def test_committed_tables_are_what_aggregate_writes_from_the_archived_runs(tmp_path, monkeypatch, capsys):
    """Regenerates every table of results/learn/runs from its archived runs (their scalars.json: seconds) into an empty
    directory and compares. The training curves' random-policy reference is a rollout per family (minutes on Walker):
    here it is the committed training_curves.csv's, so every other number of that table is regenerated.
    `python experiments/aggregate.py EMPTY_DIR results/learn/runs` recomputes it with the rollouts."""
    from experiments import aggregate

    with open(os.path.join(ARCHIVE, "training_curves.csv"), newline="") as f:
        committed_random = {(r["family"], r["train_env"]): float(r["random_policy"]) for r in csv.DictReader(f)}
    monkeypatch.setattr(aggregate, "random_policy_return", lambda family, env_id: committed_random[(family, str(env_id))])
    aggregate.main([str(tmp_path), ARCHIVE])  # an empty first root: the tables go there, the runs come from the archive
    capsys.readouterr()
    for name in TABLES + CSVS:
        assert read(str(tmp_path / name)) == read(os.path.join(ARCHIVE, name)), f"{name} differs from a regenerated one"
