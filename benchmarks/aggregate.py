"""Aggregate a sweep: read each run's TensorBoard events, group runs that differ only by seed,
and report mean and 95% Student-t CI across seeds as CSV and a markdown table.

    python benchmarks/aggregate.py runs/sweeps/cpu      # writes summary.csv, curves.csv, summary.md there

Metrics per run (keys written by every method script):
  online_return / online_success   mean over all Exp 1 test-time episodes (family average;
                                   success only for Meta-World families)
  offline_return / offline_success Exp 2 at each sweep point x = offline gradient steps
                                   (CLAW, FiLM, Concat: x = 0, their single adaptation pass)
  online_return_env{j}             Exp 1 return in environment j alone
Curves (Exp 1): family-averaged return and success per test-time step, averaged across seeds.
Training curves (experiment budget: one embodiment per run, no evaluation protocol): the mean
training-episode return per window of agent steps, per seed, then mean and 95% CI across seeds,
beside the random policy's return (training_curves.csv / training_curves.md).
Runs that failed, are still running (their run.lock is held), died, or lack evaluation events are listed,
never dropped silently; so are runs whose events repeat a step (a resume logged without purge_step), of
which the last value counts.
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import math
import os
import sys
from collections import defaultdict

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

from benchmarks.experiments import run_is_live  # noqa: E402
from common.evaluation import mean_ci  # noqa: E402

GROUP_KEYS = ("method", "family", "size", "rank")
SUCCESS_FAMILIES = ("reach", "push")  # Meta-World reports success; elsewhere the scripts log a constant 0


def reported_keys(family: str) -> tuple[str, ...]:
    return ("return", "success") if family in SUCCESS_FAMILIES else ("return",)


def eval_tag(phase: str, key: str) -> str:
    """TensorBoard tag the scripts log a metric under, e.g. eval/online/episodic_return."""
    return f"eval/{phase}/{'episodic_return' if key == 'return' else key}"


def load_runs(root: str) -> list[dict]:
    """run.json of every run under root, with its scalars as {tag: [(step, value), ...]}."""
    runs = []
    for path in sorted(glob.glob(os.path.join(root, "*", "run.json"))):
        with open(path) as f:
            run = json.load(f)
        run["dir"] = os.path.dirname(path)
        events = EventAccumulator(run["dir"], size_guidance={"scalars": 0}).Reload()
        run["scalars"], run["duplicated"] = {}, []
        for tag in events.Tags()["scalars"]:
            steps = [(e.step, e.value) for e in events.Scalars(tag)]
            if len({step for step, _ in steps}) < len(steps):  # e.g. a resume logged without purge_step
                run["duplicated"].append(tag)
            run["scalars"][tag] = sorted(dict(steps).items())  # the last value written at a step wins, as in TensorBoard
        runs.append(run)
    return runs


def run_metrics(run: dict) -> dict:
    """{(metric, x): value} of one run; x is None for scalars without a sweep axis."""
    scalars, metrics = run["scalars"], {}
    for key in reported_keys(run.get("family")):
        online = scalars.get(eval_tag("online", key), [])
        if online:
            metrics[(f"online_{key}", None)] = sum(v for _, v in online) / len(online)
        for step, value in scalars.get(eval_tag("offline", key), []):
            metrics[(f"offline_{key}", step)] = value
    for tag, values in scalars.items():  # per environment, e.g. Exp 5 scores Cheetah (env 0) alone
        parts = tag.split("/")
        if len(parts) == 4 and parts[:2] == ["eval", "online"] and parts[3] == "episodic_return":
            metrics[(f"online_return_{parts[2]}", None)] = sum(v for _, v in values) / len(values)
    return metrics


def problem(run: dict) -> str | None:
    """Why a run cannot be aggregated, or None."""
    if run_is_live(run["dir"]):
        return "still running (a live process holds its run.lock)"
    if run.get("status") == "running":
        return "status running, but no live process holds its run.lock: it died; rerun the launcher to resume it"
    if run.get("status") != "done":
        return f"status {run.get('status', 'unknown')}" + (f" (returncode {run['returncode']})" if "returncode" in run else "")
    if "budget" in run.get("experiments", []):
        return "a training curve (experiment budget), in training_curves.csv"
    if not run_metrics(run):
        return "finished without evaluation events"
    return None


def summarize(runs: list[dict]) -> tuple[list[dict], list[dict], list[tuple[str, str]]]:
    """-> summary rows, curve rows, [(run dir, problem)]."""
    groups, problems = defaultdict(list), []
    for run in runs:
        issue = problem(run)
        if issue:
            problems.append((run["dir"], issue))
        else:
            groups[tuple(run[k] for k in GROUP_KEYS)].append(run)
    rows, curves = [], []
    for key, members in sorted(groups.items(), key=lambda kv: tuple(str(k) for k in kv[0])):
        per_metric = defaultdict(list)
        for run in members:
            for metric, value in run_metrics(run).items():
                per_metric[metric].append(value)
        for (metric, x), values in sorted(per_metric.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0)):
            mean, half = mean_ci(values)
            rows.append({**dict(zip(GROUP_KEYS, key)), "metric": metric, "x": x, "n": len(values), "mean": mean, "ci95": half,
                         "seeds": ",".join(str(r["seed"]) for r in members)})
        for metric in reported_keys(key[GROUP_KEYS.index("family")]):
            by_step = defaultdict(list)
            for run in members:
                for step, value in run["scalars"].get(eval_tag("online", metric), []):
                    by_step[step].append(value)
            for step, values in sorted(by_step.items()):
                mean, half = mean_ci(values)
                curves.append({**dict(zip(GROUP_KEYS, key)), "metric": f"online_{metric}",
                               "step": step, "n": len(values), "mean": mean, "ci95": half})
    return rows, curves, problems


def train_env_of(run: dict) -> int | None:
    """ST's --train-env-id from the recorded command (the budget recipe trains one embodiment per run)."""
    words = run.get("command", "").split()
    return int(words[words.index("--train-env-id") + 1]) if "--train-env-id" in words else None


def random_policy_return(family: str, env_id: int, episodes: int = 10, seed: int = 0) -> float:
    """Mean return of uniformly random actions (the reference a learning curve must leave behind)."""
    from common.envs import make_env

    env, returns = make_env(family, env_id, seed=seed), []
    env.action_space.seed(seed)
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return sum(returns) / len(returns)


def training_curves(runs: list[dict], window: int = 2500) -> list[dict]:
    """Learning curves of the budget runs, finished or not: the mean training-episode return (charts/episodic_return,
    the planner with its exploration noise) per window of `window` agent steps, per seed, then across seeds."""
    groups = defaultdict(list)
    for run in runs:
        if "budget" in run.get("experiments", []):
            groups[(run["method"], run["family"], train_env_of(run), run["size"])].append(run)
    rows = []
    for (method, family, env_id, size), members in sorted(groups.items(), key=lambda kv: str(kv[0])):
        by_window = defaultdict(list)
        for run in members:
            per_window = defaultdict(list)
            for step, value in run["scalars"].get("charts/episodic_return", []):
                per_window[math.ceil(step / window) * window].append(value)
            for end, values in per_window.items():
                by_window[end].append(sum(values) / len(values))
        random_return = random_policy_return(family, env_id)
        for end, values in sorted(by_window.items()):
            mean, half = mean_ci(values)
            rows.append({"method": method, "family": family, "train_env": env_id, "size": size, "step": end, "n": len(values),
                         "mean": mean, "ci95": half, "random_policy": random_return, "seeds": ",".join(str(r["seed"]) for r in members)})
    return rows


def training_markdown(rows: list[dict]) -> str:
    lines = ["| method | family | env | size | agent steps up to | seeds | mean training-episode return | 95% CI | x random policy |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = r["mean"] / r["random_policy"] if r["random_policy"] > 0 else float("nan")
        lines.append(f"| {r['method']} | {r['family']} | {r['train_env']} | {r['size']} | {r['step']} | {r['n']} | {r['mean']:.1f} | "
                     f"± {r['ci95']:.1f} | {ratio:.1f} (random {r['random_policy']:.1f}) |")
    return "\n".join(lines) + "\n"


def write_csv(path: str, rows: list[dict]):
    if not rows:
        return
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def markdown(rows: list[dict], problems: list[tuple[str, str]], duplicated: list[tuple[str, list]] = ()) -> str:
    lines = ["| method | family | size | rank | metric | x | seeds | mean | 95% CI |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        x = "" if r["x"] is None else r["x"]
        lines.append(f"| {r['method']} | {r['family']} | {r['size']} | {r['rank']} | {r['metric']} | {x} | {r['n']} | "
                     f"{r['mean']:.1f} | ± {r['ci95']:.1f} |")
    if problems:
        lines += ["", "Runs not aggregated:", ""] + [f"- `{os.path.basename(d)}`: {why}" for d, why in problems]
    if duplicated:
        lines += ["", "Runs with duplicated TensorBoard steps (last value per step kept):", ""]
        lines += [f"- `{os.path.basename(d)}`: {', '.join(tags)}" for d, tags in duplicated]
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", help="sweep directory, e.g. runs/sweeps/cpu")
    cli = parser.parse_args(argv)
    runs = load_runs(cli.root)
    if not runs:
        raise SystemExit(f"error: no run.json under {cli.root!r}; run benchmarks/experiments.py first")
    rows, curves, problems = summarize(runs)
    write_csv(os.path.join(cli.root, "summary.csv"), rows)
    write_csv(os.path.join(cli.root, "curves.csv"), curves)
    training = training_curves(runs)
    if training:
        write_csv(os.path.join(cli.root, "training_curves.csv"), training)
        with open(os.path.join(cli.root, "training_curves.md"), "w") as f:
            f.write(training_markdown(training))
        print(training_markdown(training))
    duplicated = [(run["dir"], run["duplicated"]) for run in runs if run["duplicated"]]
    for run_dir, tags in duplicated:
        print(f"warning: {run_dir} has duplicated steps in {len(tags)} tag(s), e.g. {tags[0]}; kept the last value per step")
    table = markdown(rows, problems, duplicated)
    with open(os.path.join(cli.root, "summary.md"), "w") as f:
        f.write(table)
    print(table)
    print(f"{len(runs)} runs, {len(problems)} not aggregated; wrote summary.csv, curves.csv, summary.md in {cli.root}")


if __name__ == "__main__":
    main()
