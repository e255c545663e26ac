"""One-command recipes for the paper's Experiments 1-5, and the sweep launcher that runs them.

    python benchmarks/experiments.py exp1 --dry-run            # list the commands (paper scale)
    python benchmarks/experiments.py exp1 exp2 --scale cpu --workers 2
    python benchmarks/aggregate.py runs/sweeps/cpu             # tables with 95% CIs
    python benchmarks/figures.py runs/sweeps/cpu               # the paper's figures

Every run is an ordinary script invocation with its own --run-dir under runs/sweeps/{scale}/.
The launcher writes run.json beside each run (method, family, size, rank, seed, command, status);
a run whose status is "done" is skipped, and a run with a checkpoint but no "done" is resumed
with --resume. Exp 1 and Exp 2 share pretraining runs (each run evaluates both protocols), and
Exp 3, 4 and 5 share the size-F CLAW runs, so a run needed by several experiments runs once.

Scales:
  paper  the paper's tables: families, sizes, ranks, budgets, 5 seeds (GPU work).
  cpu    fits in about two hours on a 2-core CPU with --workers 2: Reach only for Exp 1/2 and
         Cheetah/Walker for Exp 3-5, sizes G-I, 5,000 pretraining steps, a 128-sample
         planner, short evaluations, 3 seeds. Same hyperparameters for every method.
  smoke  seconds-long runs used by the tests.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = {m: f"{m}_tdmpc2.py" for m in ("claw", "dr", "st", "oracle", "film", "concat", "posthoc")}
# Paper Table "Experiment 3 model-size sweep": LoRA rank tied to size.
SIZE_RANKS = {"A": 16, "B": 16, "D": 16, "E": 16, "F": 8, "G": 4, "H": 2, "I": 1}

SCALES = {
    "paper": {
        "seeds": (1, 2, 3, 4, 5),
        "exp12_families": ("walker", "reach", "push", "go1"),
        "exp12_size": "A", "exp12_rank": 16,
        "exp3_sizes": tuple(SIZE_RANKS), "exp4_size": "F", "exp4_ranks": (1, 2, 4, 8, 16, 32),
        "common": [],
        "exp345": ["--online-eval-steps", "5000"],  # 10 episodes of 500 agent steps, re-adapting every step
    },
    "cpu": {
        "seeds": (1, 2, 3),
        "exp12_families": ("reach",),
        "exp12_size": "G", "exp12_rank": 4,
        "exp3_sizes": ("G", "H", "I"), "exp4_size": "H", "exp4_ranks": (1, 4, 16),
        "common": ["--total-timesteps", "5000", "--seed-steps", "1000", "--burst-updates", "500",
                   "--num-samples", "128", "--num-elites", "16", "--num-pi-trajs", "8", "--iterations", "4",
                   "--eval-episodes", "3", "--log-every", "500", "--checkpoint-every", "1000"],
        "exp12": ["--online-eval-steps", "600", "--offline-adapt-steps", "0", "1", "10", "100"],
        "exp345": ["--online-eval-steps", "1000"],
    },
    "smoke": {
        "seeds": (1, 2),
        "exp12_families": ("reach",),
        "exp12_size": "I", "exp12_rank": 2,
        "exp3_sizes": ("I",), "exp4_size": "I", "exp4_ranks": (1, 2),
        "common": ["--total-timesteps", "620", "--seed-steps", "100", "--burst-updates", "2", "--batch-size", "16",
                   "--num-samples", "16", "--num-elites", "4", "--num-pi-trajs", "2", "--iterations", "1",
                   "--context-pool-episodes", "2", "--context-episodes", "1",
                   "--eval-episodes", "1", "--log-every", "10"],
        "exp12": ["--online-eval-steps", "100", "--offline-adapt-steps", "0", "1"],
        "exp345": ["--online-eval-steps", "100", "--total-timesteps", "1100"],  # beyond cheetah_walker's 1000-step prefill (last flag wins)
    },
}


@dataclass
class Run:
    method: str
    family: str
    size: str
    rank: int
    seed: int
    extra: list = field(default_factory=list)
    experiments: list = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"{self.method}__{self.family}__{self.size}__r{self.rank}__s{self.seed}"

    def command(self, run_dir: str) -> list[str]:
        family = [] if self.method == "posthoc" else ["--family", self.family]
        rank = [] if self.method in ("film", "concat") else ["--rank", str(self.rank)]  # no LoRA, no rank
        return [sys.executable, os.path.join(REPO, SCRIPTS[self.method]), *family, "--model-size", self.size,
                *rank, "--seed", str(self.seed), "--no-cuda", "--run-dir", run_dir, *self.extra]


def recipe(experiment: str, scale: str) -> list[Run]:
    s = SCALES[scale]
    runs = []
    if experiment in ("exp1", "exp2"):
        for family in s["exp12_families"]:
            for method in ("claw", "dr", "st", "oracle"):
                for seed in s["seeds"]:
                    extra = s.get("exp12", []) if method != "claw" else _without_sweep(s.get("exp12", []))
                    runs.append(Run(method, family, s["exp12_size"], s["exp12_rank"], seed, s["common"] + extra))
    elif experiment == "exp3":
        for size in s["exp3_sizes"]:
            for method in ("claw", "film", "concat"):
                for seed in s["seeds"]:
                    runs.append(Run(method, "cheetah_walker", size, SIZE_RANKS[size], seed, s["common"] + s["exp345"]))
    elif experiment == "exp4":
        for seed in s["seeds"]:
            for rank in s["exp4_ranks"]:
                runs.append(Run("claw", "cheetah_walker", s["exp4_size"], rank, seed, s["common"] + s["exp345"]))
            for method in ("film", "concat"):
                runs.append(Run(method, "cheetah_walker", s["exp4_size"], SIZE_RANKS[s["exp4_size"]], seed, s["common"] + s["exp345"]))
    elif experiment == "exp5":
        size = s["exp4_size"]
        for seed in s["seeds"]:
            for method in ("claw", "posthoc"):
                runs.append(Run(method, "cheetah_walker", size, SIZE_RANKS[size], seed, s["common"] + s["exp345"]))
    else:
        raise SystemExit(f"error: unknown experiment {experiment!r}; valid: exp1 exp2 exp3 exp4 exp5")
    for run in runs:
        run.experiments.append(experiment)
    return runs


def _without_sweep(extra: list) -> list:
    """CLAW adapts with one hypernet pass: it takes no --offline-adapt-steps."""
    if "--offline-adapt-steps" not in extra:
        return extra
    start = extra.index("--offline-adapt-steps")
    end = start + 1
    while end < len(extra) and not extra[end].startswith("--"):
        end += 1
    return extra[:start] + extra[end:]


def plan_runs(experiments: list[str], scale: str) -> list[Run]:
    """All runs of the experiments, each distinct run once (shared runs list every experiment)."""
    unique: dict[str, Run] = {}
    for experiment in experiments:
        for run in recipe(experiment, scale):
            if run.name in unique:
                unique[run.name].experiments.append(experiment)
            else:
                unique[run.name] = run
    return list(unique.values())


def read_status(run_dir: str) -> dict:
    path = os.path.join(run_dir, "run.json")
    if not os.path.isfile(path):
        return {}
    with open(path) as f:
        return json.load(f)


def write_status(run_dir: str, run: Run, command: list[str], status: str, **extra):
    os.makedirs(run_dir, exist_ok=True)
    record = {"method": run.method, "family": run.family, "size": run.size, "rank": run.rank, "seed": run.seed,
              "experiments": run.experiments, "command": shlex.join(command), "status": status, **extra}
    with open(os.path.join(run_dir, "run.json.tmp"), "w") as f:
        json.dump(record, f, indent=1)
    os.replace(os.path.join(run_dir, "run.json.tmp"), os.path.join(run_dir, "run.json"))


def launch(runs: list[Run], root: str, workers: int, dry_run: bool) -> int:
    """Run every unfinished run with at most `workers` processes; returns the number that failed."""
    pending = []
    for run in runs:
        run_dir = os.path.join(root, run.name)
        command = run.command(run_dir)
        checkpoint = os.path.join(run_dir, "checkpoint.pt")
        status = read_status(run_dir).get("status")
        if status == "done":
            print(f"skip (done)  {run.name}")
            continue
        if os.path.isfile(checkpoint):
            command += ["--resume", checkpoint]
        print(("resume " if "--resume" in command else "run    ") + shlex.join(command))
        pending.append((run, run_dir, command))
    if dry_run or not pending:
        return 0
    # small networks: cores/workers BLAS/OpenMP threads per run, or parallel runs thrash each
    # other's threads; an OMP_NUM_THREADS already set (e.g. beside another sweep) wins
    threads = os.environ.get("OMP_NUM_THREADS") or str(max(1, (os.cpu_count() or 1) // workers))
    env = dict(os.environ, OMP_NUM_THREADS=threads, MUJOCO_GL=os.environ.get("MUJOCO_GL", "disable"))
    active, failed = [], 0
    while pending or active:
        while pending and len(active) < workers:
            run, run_dir, command = pending.pop(0)
            write_status(run_dir, run, command, "running")
            log = open(os.path.join(run_dir, "stdout.log"), "a")
            active.append((run, run_dir, command, subprocess.Popen(command, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT), log, time.time()))
        time.sleep(1.0)
        for item in list(active):
            run, run_dir, command, process, log, start = item
            if process.poll() is None:
                continue
            active.remove(item)
            log.close()
            status = "done" if process.returncode == 0 else "failed"
            failed += status == "failed"
            write_status(run_dir, run, command, status, returncode=process.returncode, seconds=round(time.time() - start, 1))
            print(f"{status:6s} {run.name} ({time.time() - start:.0f} s)", flush=True)
    return failed


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiments", nargs="+", choices=["exp1", "exp2", "exp3", "exp4", "exp5"])
    parser.add_argument("--scale", choices=list(SCALES), default="paper")
    parser.add_argument("--workers", type=int, default=1, help="parallel runs")
    parser.add_argument("--root", default=None, help="sweep directory (default runs/sweeps/{scale})")
    parser.add_argument("--methods", nargs="+", choices=list(SCRIPTS), default=None, help="only these methods' runs")
    parser.add_argument("--dry-run", action="store_true", help="list the commands and exit")
    cli = parser.parse_args(argv)
    if cli.workers < 1:
        raise SystemExit(f"error: --workers must be >= 1, got {cli.workers}")
    root = cli.root or os.path.join("runs", "sweeps", cli.scale)
    if os.path.exists(root) and not os.path.isdir(root):
        raise SystemExit(f"error: --root {root!r} exists and is not a directory")
    runs = [r for r in plan_runs(cli.experiments, cli.scale) if cli.methods is None or r.method in cli.methods]
    print(f"{len(runs)} runs for {' '.join(cli.experiments)} at scale {cli.scale} in {root}")
    failed = launch(runs, os.path.abspath(root), cli.workers, cli.dry_run)
    if failed:
        raise SystemExit(f"{failed} run(s) failed; see their stdout.log and run.json")


if __name__ == "__main__":
    main()
