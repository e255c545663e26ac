"""Aggregate a sweep: read each run's TensorBoard events, group runs that differ only by seed,
and report mean and 95% Student-t CI across seeds, beside each seed's value, as CSV and a markdown table.

    python experiments/aggregate.py runs/sweeps/cpu      # writes summary.csv, curves.csv, summary.md there

Metrics per run (keys written by every method script):
  online_return / online_success   mean over all Exp 1 test-time episodes (family average;
                                   success only for Meta-World families)
  offline_return / offline_success Exp 2 at each sweep point x = offline gradient steps
                                   (CLAW, FiLM, Concat: x = 0, their single adaptation pass)
  online_return_env{j}             Exp 1 return in environment j alone
  offline_return_env{j}            Exp 2 in environment j alone, for families of two environments (Go1, Cheetah/Walker)
Curves (Exp 1): family-averaged return and success per test-time step, averaged across seeds.
Training curves (the budget recipe's ST runs, one embodiment per run, and every Exp 1/2 run): the mean
training-episode return (and success) per window of agent steps, per seed, then mean and 95% CI across
seeds, beside the random policy's return (training_curves.csv / training_curves.md).
Runs that failed, are still running (their run.lock is held), died, lack evaluation events, or whose run.json or
scalars.json is damaged (truncated, invalid: a warning line names the file) are listed, never dropped silently; so
are runs whose events repeat a step (a resume logged without purge_step), of which the last value counts.
"""

from __future__ import annotations

import argparse
import csv
import functools
import glob
import math
import os
import sys
from collections import defaultdict

import scipy.stats

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from common.evaluation import mean_ci  # noqa: E402
from experiments.archive import RUN_KEYS, DamagedRun, archive_sweep, read_json, read_scalars  # noqa: E402
from experiments.sweep import CONTROLS, SIZE_RANKS, run_is_live  # noqa: E402

GROUP_KEYS = ("method", "family", "size", "rank")
SUCCESS_FAMILIES = ("reach", "push")  # Meta-World reports success; elsewhere the scripts log a constant 0


def reported_keys(family: str) -> tuple[str, ...]:
    return ("return", "success") if family in SUCCESS_FAMILIES else ("return",)


def eval_tag(phase: str, key: str) -> str:
    """TensorBoard tag the scripts log a metric under, e.g. eval/online/episodic_return."""
    return f"eval/{phase}/{'episodic_return' if key == 'return' else key}"


def check_roots(tool: str, roots: list[str]) -> None:
    """One error line for a root that is not an existing directory, before anything is read or written."""
    for root in roots:
        if not os.path.isdir(root):
            what = "is not a directory" if os.path.exists(root) else "does not exist"
            raise SystemExit(f"error: {root} {what}; {tool} reads sweep directories or archives (e.g. runs/sweeps/cpu)")


def load_sweep(tool: str, roots: list[str]) -> tuple[list[dict], list[tuple[str, str]]]:
    """load_runs(roots), [(run dir, why) of the damaged runs]; one error line where no run is readable."""
    damaged = []
    runs = load_runs(roots, damaged)
    if not runs:
        readable = f"no readable run.json ({len(damaged)} damaged)" if damaged else "no run.json"
        raise SystemExit(f"error: {readable} under {' '.join(roots)}; {tool} needs runs of experiments/sweep.py")
    return runs, damaged


def load_runs(roots: str | list[str], damaged: list | None = None) -> list[dict]:
    """run.json of every run under the roots (sweep directories or archives, experiments/archive.py), with its scalars
    as {tag: [(step, value), ...]}. A run found under several roots counts once: its finished copy, else the first.
    A run whose run.json or scalars.json cannot be read is left out with a warning line naming the file, and appended
    to damaged as (run dir, why)."""
    found = {}

    def skip(run_dir: str, error: DamagedRun):
        print(f"warning: skipped a damaged run: {error}; the other runs go on", file=sys.stderr)
        if damaged is not None:
            damaged.append((run_dir, f"damaged: {error}"))

    for root in [roots] if isinstance(roots, str) else roots:
        for path in sorted(glob.glob(os.path.join(root, "*", "run.json"))):
            try:
                run = read_json(path, RUN_KEYS)
            except DamagedRun as error:
                skip(os.path.dirname(path), error)
                continue
            run["dir"] = os.path.dirname(path)
            name = os.path.basename(run["dir"])
            if name not in found or (found[name].get("status") != "done" and run.get("status") == "done"):
                found[name] = run
    runs = []
    for name in sorted(found):
        try:
            found[name]["scalars"], found[name]["duplicated"] = read_scalars(found[name]["dir"])
        except DamagedRun as error:
            skip(found[name]["dir"], error)
            continue
        runs.append(found[name])
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
    per_env = {}  # {(protocol, "env{j}"): points}
    for tag, values in scalars.items():
        parts = tag.split("/")
        if len(parts) == 4 and parts[0] == "eval" and parts[3] == "episodic_return":
            per_env[(parts[1], parts[2])] = values
    # with two environments (Go1's directions) the family mean hides which one a method fails, also offline
    offline_too = len({env for _, env in per_env}) <= 2
    for (protocol, env), values in per_env.items():  # per environment, e.g. Exp 5 scores Cheetah (env 0) alone
        if protocol == "online":
            metrics[(f"online_return_{env}", None)] = sum(v for _, v in values) / len(values)
        elif protocol == "offline" and offline_too:
            for step, value in values:
                metrics[(f"offline_return_{env}", step)] = value
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
    if run.get("method") in CONTROLS:
        return "context controls (evaluation only), in controls.md"
    if not run_metrics(run):
        return "finished without evaluation events"
    return None


def group_runs(runs: list[dict]) -> tuple[dict, list[tuple[str, str]]]:
    """-> {(method, family, size, rank): [runs that differ only by seed]}, [(run dir, why it is not aggregated)]."""
    groups, problems = defaultdict(list), []
    for run in runs:
        issue = problem(run)
        if issue:
            problems.append((run["dir"], issue))
        else:
            groups[tuple(run[k] for k in GROUP_KEYS)].append(run)
    return groups, problems


def summarize(runs: list[dict]) -> tuple[list[dict], list[dict], list[tuple[str, str]]]:
    """-> summary rows, curve rows, [(run dir, problem)]."""
    groups, problems = group_runs(runs)
    rows, curves = [], []
    for key, members in sorted(groups.items(), key=lambda kv: tuple(str(k) for k in kv[0])):
        for (metric, x), by_seed in sorted(_by_metric(members).items(), key=lambda kv: (kv[0][0], kv[0][1] or 0)):
            seeds = sorted(by_seed)
            mean, half = mean_ci([by_seed[s] for s in seeds])
            # each seed's value beside the mean: RESULTS quotes them, and they are what a new seed is compared with
            rows.append(
                {
                    **dict(zip(GROUP_KEYS, key)),
                    "metric": metric,
                    "x": x,
                    "n": len(seeds),
                    "mean": mean,
                    "ci95": half,
                    "seeds": ",".join(map(str, seeds)),
                    "per_seed": ",".join(f"{by_seed[s]:.10g}" for s in seeds),
                }
            )
        for metric in reported_keys(key[GROUP_KEYS.index("family")]):
            by_step = defaultdict(list)
            for run in members:
                for step, value in run["scalars"].get(eval_tag("online", metric), []):
                    by_step[step].append(value)
            for step, values in sorted(by_step.items()):
                mean, half = mean_ci(values)
                curves.append(
                    {
                        **dict(zip(GROUP_KEYS, key)),
                        "metric": f"online_{metric}",
                        "step": step,
                        "n": len(values),
                        "mean": mean,
                        "ci95": half,
                    }
                )
    return rows, curves, problems


TRAINING_EXPERIMENTS = ("budget", "exp1", "exp2", "decoder")  # whose runs' training episodes are compared across methods


def train_env_of(run: dict) -> int | str:
    """The environment a run trains on: ST's --train-env-id (0 by default; the budget recipe trains one embodiment per
    run), "all" for the methods that train on every environment of the family."""
    if run.get("method") != "st":
        return "all"
    words = run.get("command", "").split()
    return int(words[words.index("--train-env-id") + 1]) if "--train-env-id" in words else 0


@functools.cache  # every method's curve on a family shares one reference: roll it out once (minutes on Walker)
def random_policy_return(family: str, env_id: int | str, episodes: int = 10, seed: int = 0) -> float:
    """Mean return of uniformly random actions (the reference a learning curve must leave behind); env_id "all":
    the mean over the family's environments, about 20 episodes in all (at least 2 each)."""
    from common.envs import make_env, num_envs

    if env_id == "all":
        n = num_envs(family)
        each = max(2, math.ceil(20 / n))  # Go1's two directions: 10 each, the per-direction reference itself
        return sum(random_policy_return(family, j, episodes=each, seed=seed) for j in range(n)) / n
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
    """Learning curves of the budget and Exp 1/2 runs (decoder recipe included), finished or not: the mean
    training-episode return (charts/episodic_return: the planner with its exploration noise), and success where the
    family has one, per window of `window` agent steps, per seed, then across seeds; one curve per method, family
    and training environment (ST: its one; the others: "all")."""
    groups = defaultdict(list)
    for run in runs:
        if set(run.get("experiments", [])) & set(TRAINING_EXPERIMENTS) and run.get("method") not in CONTROLS:
            groups[(run["method"], run["family"], train_env_of(run), run["size"])].append(run)
    rows = []
    for (method, family, env_id, size), members in sorted(groups.items(), key=lambda kv: str(kv[0])):
        by_window = {key: defaultdict(list) for key in reported_keys(family)}
        for run in members:
            for key in by_window:
                per_window = defaultdict(list)
                for step, value in run["scalars"].get(f"charts/episodic_{key}", []):
                    per_window[math.ceil(step / window) * window].append(value)
                for end, values in per_window.items():
                    by_window[key][end].append(sum(values) / len(values))
        if not by_window["return"]:
            continue
        random_return = random_policy_return(family, env_id)
        for end, values in sorted(by_window["return"].items()):
            mean, half = mean_ci(values)
            success = by_window.get("success", {}).get(end)
            rows.append(
                {
                    "method": method,
                    "family": family,
                    "train_env": env_id,
                    "size": size,
                    "step": end,
                    "n": len(values),
                    "mean": mean,
                    "ci95": half,
                    "success": sum(success) / len(success) if success else math.nan,
                    "random_policy": random_return,
                    "seeds": ",".join(str(r["seed"]) for r in members),
                }
            )
    return rows


def ci_cell(half: float) -> str:
    """A table's CI cell: a single sample has no interval (mean_ci's NaN), said in words."""
    return "none (one sample)" if math.isnan(half) else f"± {half:.1f}"


def training_markdown(rows: list[dict]) -> str:
    lines = [
        "| method | family | env | size | agent steps up to | seeds | mean training-episode return | 95% CI | x random policy | success |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ratio = r["mean"] / r["random_policy"] if r["random_policy"] > 0 else float("nan")
        success = "" if math.isnan(r["success"]) else f"{r['success']:.2f}"
        lines.append(
            f"| {r['method']} | {r['family']} | {r['train_env']} | {r['size']} | {r['step']} | {r['n']} | {r['mean']:.1f} | "
            f"{ci_cell(r['ci95'])} | {ratio:.1f} (random {r['random_policy']:.1f}) | {success} |"
        )
    return "\n".join(lines) + "\n"


def controls_rows(runs: list[dict]) -> list[dict]:
    """Context controls (diagnostics/context_controls.py on the Exp 1/2 checkpoints of CLAW, or of CLAW + decoder), per
    trained method and family: each seed's family-mean return with its own context, with another environment's, their
    difference, and per context size; then mean and 95% CI across seeds, and across (seed, environment) pairs (more
    pairs, but environments of one seed share a network, so this CI is the optimistic one)."""
    groups = defaultdict(list)
    for run in runs:
        path = os.path.join(run["dir"], "controls.json")
        if run.get("method") in CONTROLS and run.get("status") == "done" and os.path.isfile(path):
            try:
                result = read_json(path, ("context_episodes", "swap", "size"))
            except DamagedRun as error:
                print(f"warning: skipped the controls of {os.path.basename(run['dir'])}: {error}", file=sys.stderr)
                continue
            groups[(CONTROLS[run["method"]], run["family"], run["size"], run["rank"])].append((run["seed"], result))
    rows = []
    for (method, family, size, rank), members in sorted(groups.items()):
        # (quantity, protocol, arm, context episodes) -> (per-seed means, per-(seed, env) values)
        quantities = defaultdict(lambda: ([], []))

        def add(key: tuple, per_env: dict):
            values = [v for v in per_env.values() if not math.isnan(v)]  # online: an environment without a finished episode
            if values:
                quantities[key][0].append(sum(values) / len(values))
                quantities[key][1].extend(values)

        for _, result in members:
            k = result["context_episodes"]
            for protocol in result["swap"]["own"]:
                own, swapped = result["swap"]["own"][protocol], result["swap"]["swapped"][protocol]
                add((f"{protocol}: own context ({k} episodes)", protocol, "own", k), own)
                add((f"{protocol}: another environment's context", protocol, "another", k), swapped)
                add((f"{protocol}: own - another's", protocol, "own - another", k), {e: own[e] - swapped[e] for e in own})
            for episodes, per_env in sorted(result["size"].items(), key=lambda kv: int(kv[0])):
                add((f"offline: {episodes}-episode own context", "offline", "size", int(episodes)), per_env)
        for (name, protocol, arm, episodes), (per_seed, per_pair) in quantities.items():
            mean, half = mean_ci(per_seed)
            _, pair_half = mean_ci(per_pair)
            rows.append(
                {
                    "method": method,
                    "family": family,
                    "size": size,
                    "rank": rank,
                    "quantity": name,
                    "protocol": protocol,
                    "arm": arm,
                    "context_episodes": episodes,
                    "n_seeds": len(per_seed),
                    "mean": mean,
                    "ci95_seeds": half,
                    "n_pairs": len(per_pair),
                    "ci95_pairs": pair_half,
                    "seeds": ",".join(str(seed) for seed, _ in members),
                }
            )
    return rows


def controls_markdown(rows: list[dict]) -> str:
    lines = [
        "| method | family | size | rank | quantity | seeds | mean return | 95% CI across seeds | (seed, env) pairs | 95% CI across pairs |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['family']} | {r['size']} | {r['rank']} | {r['quantity']} | {r['n_seeds']} | {r['mean']:.1f} | "
            f"{ci_cell(r['ci95_seeds'])} | {r['n_pairs']} | {ci_cell(r['ci95_pairs'])} |"
        )
    return "\n".join(lines) + "\n"


# The paper's claims, each tested on the runs at hand. A comparison "a > b" supports the claim when the 95% CI of
# a - b lies above 0, contradicts it when it lies below 0, and cannot separate them otherwise. "a tracks b" (CLAW vs the
# oracle) supports when a - b's CI lies above -TRACK_MARGIN x |mean of b| (an equivalence margin), contradicts when it
# lies below 0. A claim is reproduced when every comparison supports it, not reproduced when one contradicts it.
TRACK_MARGIN = 0.10


def difference_ci(a: list[float], b: list[float], paired: bool = False) -> tuple[float, float, float]:
    """(mean of a - b, 95% CI low, high): Welch's t for independent runs, the paired t for two values per run."""
    if paired:
        diff = [x - y for x, y in zip(a, b)]
        mean, half = mean_ci(diff)
        return mean, mean - half, mean + half
    mean = sum(a) / len(a) - sum(b) / len(b)
    if len(a) < 2 or len(b) < 2:
        return mean, float("nan"), float("nan")
    low, high = scipy.stats.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    return mean, float(low), float(high)


def judge(low: float, high: float, margin: float | None = None) -> str:
    """supports / contradicts / not separable for "a > b" (margin None) or "a tracks b" (low bound -margin)."""
    if math.isnan(low):
        return "not separable"
    if high < 0:
        return "contradicts"
    return "supports" if low > (0 if margin is None else -margin) else "not separable"


def seed_values(groups: dict) -> dict:
    """{(method, family, size, rank): {(metric, x): {seed: value}}} from group_runs' groups."""
    return {key: _by_metric(members) for key, members in groups.items()}


def _by_metric(members: list[dict]) -> dict:
    values = defaultdict(dict)
    for run in members:
        for metric, value in run_metrics(run).items():
            values[metric][run["seed"]] = value
    return values


def claims(values: dict, exp4_size: str = "F", exp4_rank: int = 8) -> list[dict]:
    """The paper's claims, each with its comparisons: {"claim", "verdict", "evidence": [lines]}.

    Exp 1 and 2 are judged per family too: a family whose runs are not all there is named "runs missing" on the
    claim's "by family" line and left out of the claim's verdict, which the families with every run decide."""

    def runs_of(method, family, metric, x=None, size=None, rank=None):
        """{seed: value} of the one group that matches (size/rank None: any, if only one group matches)."""
        found = [
            v.get((metric, x), {})
            for (m, f, s, r), v in values.items()
            if m == method and f == family and size in (None, s) and rank in (None, r)
        ]
        return found[0] if len(found) == 1 else {}

    def compare(label, a: dict, b: dict, track_of=None, paired=False, family=None):
        """One comparison; family (Exp 1/2) groups it into its claim's per-family verdicts."""
        seeds = sorted(set(a) & set(b))  # a paired difference needs both values from the same seed
        if len(a) < 2 or len(b) < 2 or (paired and len(seeds) < 2):
            have = f"{len(seeds)} seed(s) with both values" if paired else f"{len(a)} vs {len(b)} seeds"
            return {"label": label, "verdict": "missing", "family": family, "text": f"{label}: runs missing ({have})"}
        if paired:
            mean, low, high = difference_ci([a[s] for s in seeds], [b[s] for s in seeds], paired=True)
            n = f"paired over {len(seeds)} seeds"
        else:
            mean, low, high = difference_ci(list(a.values()), list(b.values()))
            n = f"n = {len(a)} vs {len(b)}"
        margin = None if track_of is None else TRACK_MARGIN * abs(sum(track_of.values()) / len(track_of))
        verdict = judge(low, high, margin)
        bound = "" if margin is None else f", margin {margin:.1f}"
        return {
            "label": label,
            "verdict": verdict,
            "n": min(len(a), len(b)),
            "family": family,
            "text": f"{label}: {mean:+.1f} [{low:+.1f}, {high:+.1f}] ({n}{bound}): {verdict}",
        }

    results = []
    exp12_families = sorted({f for (m, f, s, r) in values if m in ("dr", "st", "oracle")})
    parts = []
    for family in exp12_families:
        claw = runs_of("claw", family, "online_return")
        oracle = runs_of("oracle", family, "online_return")
        parts += [
            compare(f"{family} Exp 1 return, CLAW - DR", claw, runs_of("dr", family, "online_return"), family=family),
            compare(f"{family} Exp 1 return, CLAW - ST", claw, runs_of("st", family, "online_return"), family=family),
            compare(f"{family} Exp 1 return, CLAW - Oracle (tracks)", claw, oracle, track_of=oracle, family=family),
        ]
    no_exp12 = [{"label": "exp12", "verdict": "missing", "n": 0, "text": "no finished DR, ST or Oracle run"}]
    results.append(("CLAW tracks the oracle and beats DR and ST online (Exp 1)", parts or no_exp12))
    parts = []
    for family in exp12_families:
        claw = runs_of("claw", family, "offline_return", 0)
        for method in ("dr", "st", "oracle"):
            sweep = {
                x: v
                for (m, f, s, r), groups in values.items()
                if m == method and f == family
                for (metric, x), v in groups.items()
                if metric == "offline_return"
            }
            if len(sweep) < 2:
                parts.append(compare(f"{family} Exp 2 {method.upper()}", {}, {}, family=family))
                continue
            most = max(sweep)
            peak = max((x for x in sweep if x != most), key=lambda x: sum(sweep[x].values()) / len(sweep[x]))
            parts.append(
                compare(
                    f"{family} Exp 2 {method.upper()} collapses: return at {peak} steps (its best before {most}) - at {most}",
                    sweep[peak],
                    sweep[most],
                    paired=True,
                    family=family,
                )
            )
            if method != "oracle":
                label = f"{family} Exp 2 CLAW (one pass) - {method.upper()} at {most} steps"
                parts.append(compare(label, claw, sweep[most], family=family))
    results.append(("Gradient methods collapse with many offline steps, CLAW does not (Exp 2)", parts or no_exp12))
    claw = runs_of("claw", "cheetah_walker", "online_return", size=exp4_size, rank=exp4_rank)
    results.append(
        (
            f"CLAW beats FiLM and Concat at mid sizes (Exp 3/4, size {exp4_size})",
            [
                compare(
                    f"cheetah_walker return, CLAW r{exp4_rank} - {m}",
                    claw,
                    runs_of(m, "cheetah_walker", "online_return", size=exp4_size),
                )
                for m in ("film", "concat")
            ],
        )
    )
    ranks = [
        (r, v)
        for (m, f, s, r), groups in values.items()
        if m == "claw" and f == "cheetah_walker" and s == exp4_size
        for v in groups.get(("online_return", None), {}).values()
    ]
    if len({r for r, _ in ranks}) >= 3:
        fit = scipy.stats.linregress([math.log2(r) for r, _ in ranks], [v for _, v in ranks])
        half = fit.stderr * scipy.stats.t.ppf(0.975, len(ranks) - 2)
        verdict = judge(fit.slope - half, fit.slope + half)
        part = {
            "label": "slope",
            "verdict": verdict,
            "n": len(ranks) // len({r for r, _ in ranks}),
            "text": f"cheetah_walker return per doubling of rank (least squares over {len(ranks)} runs, ranks "
            f"{sorted({r for r, _ in ranks})}): {fit.slope:+.1f} [{fit.slope - half:+.1f}, {fit.slope + half:+.1f}]: {verdict}",
        }
    else:
        part = {"label": "slope", "verdict": "missing", "text": "return vs rank: fewer than 3 ranks finished"}
    results.append((f"Return rises with LoRA rank (Exp 4, size {exp4_size})", [part]))
    results.append(
        (
            "Joint training beats the post-hoc hypernetwork (Exp 5, Cheetah)",
            [
                compare(
                    f"cheetah return, CLAW r{exp4_rank} - post-hoc",
                    runs_of("claw", "cheetah_walker", "online_return_env0", size=exp4_size, rank=exp4_rank),
                    runs_of("posthoc", "cheetah_walker", "online_return_env0", size=exp4_size),
                )
            ],
        )
    )
    # Go1's two directions (env 0 forward, env 1 backward; ST trains forward): DR's one model averages them, and
    # ST's gradient steps do not reach the backward oracle
    results.append(
        (
            "DR is good at neither Go1 direction and ST does not close the backward gap (Exp 1, Go1)",
            [
                compare(
                    f"go1 {direction} Exp 1 return, Oracle - {method.upper()}",
                    runs_of("oracle", "go1", f"online_return_env{env}"),
                    runs_of(method, "go1", f"online_return_env{env}"),
                )
                for method, env, direction in (("dr", 0, "forward"), ("dr", 1, "backward"), ("st", 1, "backward"))
            ],
        )
    )
    out = []
    for claim, parts in results:
        families = list(dict.fromkeys(p["family"] for p in parts if p.get("family")))
        by_family = {f: overall([p for p in parts if p.get("family") == f]) for f in families}
        judged = [p for p in parts if by_family.get(p.get("family")) != "runs missing"] if families else parts
        verdict = overall(judged) if judged else "runs missing"
        evidence = [p["text"] for p in parts]
        if len(families) > 1:
            evidence.insert(0, "by family: " + "; ".join(f"{f} {v}" for f, v in by_family.items()))
        out.append({"claim": claim, "verdict": verdict, "evidence": evidence})
    return out


def overall(parts: list[dict]) -> str:
    """A claim's verdict from its comparisons: reproduced when all support it, not reproduced when one contradicts."""
    verdicts = {p["verdict"] for p in parts}
    if not parts or "missing" in verdicts:
        return "runs missing"
    if "contradicts" in verdicts:
        return "not reproduced"
    if verdicts == {"supports"}:
        return "reproduced"
    return f"not separable at n = {max(p['n'] for p in parts)}"


def claims_markdown(results: list[dict]) -> str:
    lines = [
        f"Differences of means with 95% CIs (Welch's t across seeds; paired t where both values come from the same runs). "
        f"'tracks': within {TRACK_MARGIN:.0%} of the oracle's return.",
        "",
    ]
    for r in results:
        lines += [f"- **{r['claim']}: {r['verdict']}**"] + [f"  - {line}" for line in r["evidence"]]
    return "\n".join(lines) + "\n"


def write_csv(path: str, rows: list[dict]):
    if not rows:
        return
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def markdown(rows: list[dict], problems: list[tuple[str, str]], duplicated: list[tuple[str, list]] = ()) -> str:
    lines = [
        "| method | family | size | rank | metric | x | seeds | mean | 95% CI | per seed |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        x = "" if r["x"] is None else r["x"]
        per_seed = ", ".join(f"s{seed}: {float(v):.1f}" for seed, v in zip(r["seeds"].split(","), r["per_seed"].split(",")))
        lines.append(
            f"| {r['method']} | {r['family']} | {r['size']} | {r['rank']} | {r['metric']} | {x} | {r['n']} | "
            f"{r['mean']:.1f} | {ci_cell(r['ci95'])} | {per_seed} |"
        )
    if problems:
        lines += ["", "Runs not aggregated:", ""] + [f"- `{os.path.basename(d)}`: {why}" for d, why in problems]
    if duplicated:
        lines += ["", "Runs with duplicated TensorBoard steps (last value per step kept):", ""]
        lines += [f"- `{os.path.basename(d)}`: {', '.join(tags)}" for d, tags in duplicated]
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "roots",
        nargs="+",
        metavar="root",
        help="sweep directories or archives (experiments/archive.py), e.g. runs/sweeps/cpu; the tables go to the first",
    )
    parser.add_argument(
        "--archive",
        default=None,
        metavar="DIR",
        help="also read this archive, and first archive there every finished run of the roots (e.g. results/learn/runs)",
    )
    parser.add_argument(
        "--exp4-size",
        default="F",
        choices=list(SIZE_RANKS),
        help="model size of the Exp 3/4/5 claims (rank: the size's Exp 3 rank); the cpu scale's is H",
    )
    cli = parser.parse_args(argv)
    cli.root = cli.roots[0]
    check_roots("aggregate.py", cli.roots)
    if cli.archive:
        for root in [r for r in cli.roots if os.path.abspath(r) != os.path.abspath(cli.archive)]:
            print(f"archived {archive_sweep(root, cli.archive)} finished runs of {root} in {cli.archive}")
        cli.roots.append(cli.archive)
    runs, damaged = load_sweep("aggregate.py", cli.roots)
    print(
        f"read {len(runs)} runs; the training curves roll out a random policy per family (minutes on Walker)",
        file=sys.stderr,
        flush=True,
    )
    rows, curves, problems = summarize(runs)
    problems += damaged  # listed in summary.md beside the others, never dropped silently
    write_csv(os.path.join(cli.root, "summary.csv"), rows)
    write_csv(os.path.join(cli.root, "curves.csv"), curves)
    for name, table_rows, to_markdown in (
        ("training_curves", training_curves(runs), training_markdown),
        ("controls", controls_rows(runs), controls_markdown),
    ):
        if table_rows:
            write_csv(os.path.join(cli.root, f"{name}.csv"), table_rows)
            with open(os.path.join(cli.root, f"{name}.md"), "w") as f:
                f.write(to_markdown(table_rows))
            print(to_markdown(table_rows))
    verdicts = claims_markdown(claims(seed_values(group_runs(runs)[0]), cli.exp4_size, SIZE_RANKS[cli.exp4_size]))
    with open(os.path.join(cli.root, "claims.md"), "w") as f:
        f.write(verdicts)
    print(verdicts)
    duplicated = [(run["dir"], run["duplicated"]) for run in runs if run["duplicated"]]
    for run_dir, tags in duplicated:
        print(f"warning: {run_dir} has duplicated steps in {len(tags)} tag(s), e.g. {tags[0]}; kept the last value per step")
    table = markdown(rows, problems, duplicated)
    with open(os.path.join(cli.root, "summary.md"), "w") as f:
        f.write(table)
    print(table)
    print(
        f"{len(runs) + len(damaged)} runs, {len(problems)} not aggregated; wrote summary.csv, curves.csv, summary.md in {cli.root}"
    )


if __name__ == "__main__":
    main()
