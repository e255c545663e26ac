"""One-command recipes for the paper's Experiments 1-5 and the context controls, and the sweep launcher that runs them.

    python experiments/sweep.py exp1 --dry-run            # list the commands (paper scale)
    python experiments/sweep.py exp1 exp2 --scale cpu --launcher local --workers 2
    python experiments/sweep.py decoder --scale learn --families reach --seeds 2 3   # a part of a recipe first
    python experiments/sweep.py exp1 exp2 --launcher slurm --partition gpu --time 12:00:00 \
        --cpus-per-task 8 --gpus-per-task 1                   # one SLURM job array, then returns
    python experiments/aggregate.py runs/sweeps/cpu             # tables with 95% CIs
    python experiments/figures.py runs/sweeps/cpu               # the paper's figures

Every run is an ordinary script invocation with its own --run-dir under runs/sweeps/{scale}/, its
output in stdout.log there; local runs it on this machine, slurm as one task of a job array
(submitit), requeued on preemption or time-out to resume from its checkpoint. The launcher writes
run.json beside each run (method, family, size, rank, seed, experiments, command, status). With --archive DIR
(e.g. results/learn/runs, committed) each finished run's measurements and weights (not its replay buffer) are also copied to DIR
(experiments/archive.py), and the runs DIR holds are skipped: losing the sweep directory loses no finished run.
With --carry DIR (e.g. results/learn/carry, committed) an unfinished run is not lost with its machine either: each
time it saves progress its directory is copied to DIR, and a launcher whose sweep directory lacks it copies it back
and resumes it; a controls run whose CLAW run is archived evaluates the archived weights.
The process that runs a run holds run.lock in its directory (flock) for the run's lifetime, so a
restarted launcher skips runs that are "done" or live (lock held) and resumes, with --resume, those
that died (lock free, checkpoint present); it prints a finished run whose recorded command differs
from the recipe's. Exp 1 and Exp 2 share pretraining runs (each run evaluates both protocols), and
Exp 3, 4 and 5 share the size-F CLAW runs, so a run needed by several experiments runs once.
Experiment controls trains nothing: one run per Exp 1/2 family and seed evaluates that CLAW run's
checkpoint with diagnostics/context_controls.py (own vs another environment's context, context sizes 1, 3, 10),
writing controls.json and controls.md in its run directory, with each scale's Exp 1/2 evaluation settings
(SCALES[scale]["controls"]). It waits for its CLAW run: the launcher starts it once that run is "done" (rerun
the launcher later); a controls run whose checkpoint is ready starts ahead of the training runs still queued.
Experiment decoder (not in the paper) reruns Exp 1/2's CLAW runs with --decoder-coef 1.0, a reward decoder on u_con
that gives the context encoder an identification signal (RESULTS.md); its runs are method claw_decoder in the tables,
and each is followed by its context controls (method controls_decoder, the controls experiment's settings).

Scales:
  paper  the paper's tables: families, sizes, ranks, budgets, 5 seeds (GPU work).
  cpu    fits in about two hours on a 2-core CPU with --workers 2: Reach only for Exp 1/2 and
         Cheetah/Walker for Exp 3-5, sizes G-I, 5,000 pretraining steps, a 128-sample
         planner, short evaluations, 3 seeds. Same hyperparameters for every method.
  learn  budgets where single-task TD-MPC2 learns, size F, 3 seeds, compiled: `budget` (ST on each
         Cheetah/Walker embodiment, 2 seeds, 40,000 agent steps, training curves only) chose the per-embodiment
         budget of Exp 3-5: 20,000 agent steps (single-task returns 15-30x the random policy's there; RESULTS.md),
         so Exp 4 (CLAW ranks 1, 4, 8, 16, FiLM, Concat) and Exp 5 (post-hoc vs CLAW rank 8) pretrain 40,000 steps
         on Cheetah/Walker (post-hoc: 20,000 walker + 20,000 cheetah), 5,000 online test-time steps per
         environment as in the paper; Exp 3 at this scale is the size-F slice of Exp 4. Exp 1/2 on Reach (the
         paper's 50,000 steps, 2,000 online test-time steps per environment, 10 offline episodes per
         environment and sweep point) and Walker (50,000 steps, 1,000 online steps, 2 offline episodes:
         20 environments x 5 sweep points x 500-step episodes, ~100k planner calls per run).
  smoke  seconds-long runs used by the tests.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import fcntl
import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

import submitit

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)  # run as a script, experiments/ is not yet a package on the path
from experiments.archive import WEIGHTS, DamagedRun, archive_run, carry_run, is_archived, read_json, restore_run  # noqa: E402

SCRIPTS = {m: f"{m}_tdmpc2.py" for m in ("claw", "dr", "st", "oracle", "film", "concat", "posthoc")}
SCRIPTS["controls"] = os.path.join("diagnostics", "context_controls.py")  # evaluation only: Run.command
# experiment decoder: CLAW with its reward decoder on u_con (a departure from the paper), a method of its own in the tables
SCRIPTS["claw_decoder"] = SCRIPTS["claw"]
# evaluation-only methods (diagnostics/context_controls.py) -> the trained method whose checkpoints they evaluate
CONTROLS = {"controls": "claw", "controls_decoder": "claw_decoder"}
SCRIPTS["controls_decoder"] = SCRIPTS["controls"]
# what the launcher measures on a finished run's checkpoint, kept in the archive (which does not keep checkpoints):
# report file -> (diagnostics/ script whose stdout it is, the methods it applies to). context_effect: how much the
# context moves the world model's predictions (in-context methods); inspect_adapters: whether u_con and the generated
# adapters tell the environments apart, and which losses reach the context encoder (CLAW's hypernetwork)
CHECKPOINT_REPORTS = {
    "context_effect.md": ("context_effect.py", ("claw", "claw_decoder", "film", "concat", "posthoc")),
    "inspect_adapters.txt": ("inspect_adapters.py", ("claw", "claw_decoder")),
}
DECODER_FLAGS = ["--decoder-coef", "1.0"]  # chosen at the cpu scale, RESULTS.md "An identification loss"
# Paper Table "Experiment 3 model-size sweep": LoRA rank tied to size.
LOCK = "run.lock"  # held by the process that runs the run, for the run's lifetime (lock_run)
SIZE_RANKS = {"A": 16, "B": 16, "D": 16, "E": 16, "F": 8, "G": 4, "H": 2, "I": 1}

# fmt: off
SCALES = {
    "paper": {
        "seeds": (1, 2, 3, 4, 5),
        "exp12_families": ("walker", "reach", "push", "go1"),
        "exp12_size": "A", "exp12_rank": 16,
        "exp3_sizes": tuple(SIZE_RANKS), "exp4_size": "F", "exp4_ranks": (1, 2, 4, 8, 16, 32),
        "common": [],
        "exp345": ["--online-eval-steps", "5000"],  # 10 episodes of 500 agent steps, re-adapting every step
        # the CLAW runs' 10 offline episodes; no online arm: the controls run on the CPU, where 30,000 online steps
        # per environment and arm at size A do not fit
        "controls": ["--eval-episodes", "10", "--context-episodes", "1", "3", "10", "--compile", "on"],
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
        "controls": ["--eval-episodes", "3", "--online-eval-steps", "600", "--context-episodes", "1", "3", "10"],
    },
    "learn": {
        "seeds": (1, 2, 3),
        "exp12_families": ("reach", "walker", "go1", "push"),
        "exp12_size": "F", "exp12_rank": 16,
        "common": ["--compile", "on", "--log-every", "1000", "--checkpoint-every", "5000"],
        "exp12": ["--offline-adapt-steps", "0", "1", "10", "100", "1000"],
        "exp12_family": {"reach": ["--total-timesteps", "50000", "--online-eval-steps", "2000"],
                         "walker": ["--total-timesteps", "50000", "--online-eval-steps", "1000", "--eval-episodes", "2"],
                         # budgets from the budget recipe's ST runs (results/learn_budget, seeds 1 and 2): Go1's mean
                         # return about 5x the random policy's from 60,000 steps; Push's mean success 0.3-0.4 from
                         # 30,000 (seed 2 only: seed 1's stays near 0 through 100,000)
                         "push": ["--total-timesteps", "40000", "--online-eval-steps", "2000"],
                         "go1": ["--total-timesteps", "70000", "--online-eval-steps", "3000", "--eval-episodes", "2"]},
        "budget": ["--no-evaluate-after-training"], "budget_seeds": (1, 2),
        # family -> (ST's training environments, agent steps): Cheetah/Walker each embodiment; Push one goal, Go1 forward
        "budget_families": {"cheetah_walker": ((0, 1), 40000), "push": ((0,), 100000), "go1": ((0,), 100000)},
        "exp3_sizes": ("F",), "exp4_size": "F", "exp4_ranks": (1, 4, 8, 16),
        "exp345": ["--total-timesteps", "40000", "--online-eval-steps", "5000"],  # 2 x the 20,000-step budget
        # the Exp 1/2 evaluation of each family; the compiled planner: ~1.7x faster evaluation at size F
        "controls": ["--context-episodes", "1", "3", "10", "--compile", "on"],
        "controls_family": {"reach": ["--eval-episodes", "10", "--online-eval-steps", "2000"],
                            # strengths are sorted: offset 10 of 20 swaps in a strength ~0.5 away, not a neighbour 0.05 away
                            "walker": ["--eval-episodes", "2", "--online-eval-steps", "1000", "--swap-offset", "10"],
                            "push": ["--eval-episodes", "10", "--online-eval-steps", "2000"],
                            "go1": ["--eval-episodes", "2", "--online-eval-steps", "3000"]},
    },
    "look": {  # experiments/look.py: a few minutes on a 2-core CPU, to see the pipeline end to end, not to learn
        "seeds": (1, 2),
        "exp12_families": ("reach",),
        "exp12_size": "I", "exp12_rank": 2,
        "exp3_sizes": ("I",), "exp4_size": "I", "exp4_ranks": (1, 2),
        "common": ["--total-timesteps", "800", "--seed-steps", "100", "--burst-updates", "20", "--batch-size", "32",
                   "--num-samples", "32", "--num-elites", "4", "--num-pi-trajs", "2", "--iterations", "1",
                   "--context-episodes", "1", "--compile", "off", "--eval-episodes", "1", "--log-every", "200"],
        "exp12": ["--online-eval-steps", "100", "--offline-adapt-steps", "0", "1", "10"],
        "exp345": ["--online-eval-steps", "200"],
        "controls": ["--eval-episodes", "1", "--online-eval-steps", "20", "--context-episodes", "1", "2"],
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
        # two of Reach's six goals: a plumbing check, not a measurement
        "exp12": ["--online-eval-steps", "100", "--offline-adapt-steps", "0", "1", "--eval-env-ids", "0", "1"],
        # --total-timesteps beyond cheetah_walker's 1000-step prefill (last flag wins)
        "exp345": ["--online-eval-steps", "100", "--total-timesteps", "1100"],
        "controls": ["--eval-episodes", "1", "--online-eval-steps", "20", "--context-episodes", "1", "2"],
        # the CHECKPOINT_REPORTS' own flags (default: each tool's defaults)
        "reports": {"context_effect.md": ["--episodes", "1", "--draws", "2", "--batch", "8"],
                    "inspect_adapters.txt": ["--episodes", "1", "--draws", "2"]},
    },
}
# fmt: on


@dataclass
class Run:
    method: str
    family: str
    size: str
    rank: int
    seed: int
    extra: list = field(default_factory=list)
    experiments: list = field(default_factory=list)
    train_env: int | None = None  # ST's --train-env-id, where a recipe names it
    needs: str | None = None  # the run whose checkpoint this one evaluates (experiment controls)
    report_flags: dict = field(default_factory=dict)  # CHECKPOINT_REPORTS name -> the tool's flags, where not its defaults

    @property
    def name(self) -> str:
        env = "" if self.train_env is None else f"__e{self.train_env}"
        return f"{self.method}__{self.family}{env}__{self.size}__r{self.rank}__s{self.seed}"

    def command(self, run_dir: str, cuda: bool = False) -> list[str]:
        if self.method in CONTROLS:  # the checkpoint carries its run's arguments; the controls run on the CPU
            checkpoint = os.path.join(os.path.dirname(run_dir), self.needs, "checkpoint.pt")
            return [
                sys.executable,
                os.path.join(REPO, SCRIPTS[self.method]),
                checkpoint,
                *self.extra,
                "--json",
                os.path.join(run_dir, "controls.json"),
                "--out",
                os.path.join(run_dir, "controls.md"),
            ]
        family = [] if self.method == "posthoc" else ["--family", self.family]
        rank = [] if self.method in ("film", "concat") else ["--rank", str(self.rank)]  # no LoRA, no rank
        device = [] if cuda else ["--no-cuda"]
        env = [] if self.train_env is None else ["--train-env-id", str(self.train_env)]
        return [
            sys.executable,
            os.path.join(REPO, SCRIPTS[self.method]),
            *family,
            *env,
            "--model-size",
            self.size,
            *rank,
            "--seed",
            str(self.seed),
            *device,
            "--run-dir",
            run_dir,
            *self.extra,
        ]


def recipe(experiment: str, scale: str) -> list[Run]:
    s = SCALES[scale]
    runs = []
    if experiment in ("exp1", "exp2"):
        # seed-major: a sweep cut short holds every method and family at n seeds before any at n + 1
        for seed in s["seeds"]:
            for family in s["exp12_families"]:
                for method in ("claw", "dr", "st", "oracle"):
                    extra = s.get("exp12", []) if method != "claw" else _without_sweep(s.get("exp12", []))
                    extra = extra + s.get("exp12_family", {}).get(family, [])
                    runs.append(Run(method, family, s["exp12_size"], s["exp12_rank"], seed, s["common"] + extra))
    elif experiment == "decoder":  # Exp 1/2's CLAW runs again, with --decoder-coef
        for seed in s["seeds"]:
            for family in s["exp12_families"]:
                extra = _without_sweep(s.get("exp12", [])) + s.get("exp12_family", {}).get(family, []) + DECODER_FLAGS
                runs.append(Run("claw_decoder", family, s["exp12_size"], s["exp12_rank"], seed, s["common"] + extra))
        runs += controls_recipe(s, "controls_decoder")
    elif experiment == "controls":  # evaluation only: the Exp 1/2 CLAW runs' checkpoints
        runs = controls_recipe(s, "controls")
    elif experiment == "budget":  # single-task learning curves: each Cheetah/Walker embodiment, one Push goal, Go1 forward
        if "budget" not in s:
            raise SystemExit(f"error: experiment budget is defined at scale learn only, not {scale}")
        for seed in s["budget_seeds"]:  # seed-major, as Exp 1/2: a cut-short check holds every family at n seeds first
            for family, (env_ids, steps) in s["budget_families"].items():
                for env_id in env_ids:
                    extra = s["common"] + ["--total-timesteps", str(steps)] + s["budget"]
                    runs.append(Run("st", family, "F", SIZE_RANKS["F"], seed, extra, train_env=env_id))
    elif "exp345" not in s:
        raise SystemExit(f"error: {experiment} at scale {scale} waits for its per-embodiment budget (experiment budget)")
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
                runs.append(
                    Run(method, "cheetah_walker", s["exp4_size"], SIZE_RANKS[s["exp4_size"]], seed, s["common"] + s["exp345"])
                )
    elif experiment == "exp5":
        size = s["exp4_size"]
        for seed in s["seeds"]:
            for method in ("claw", "posthoc"):
                runs.append(Run(method, "cheetah_walker", size, SIZE_RANKS[size], seed, s["common"] + s["exp345"]))
    else:
        raise SystemExit(f"error: unknown experiment {experiment!r}; valid: budget controls decoder exp1 exp2 exp3 exp4 exp5")
    for run in runs:
        run.experiments.append(experiment)
        run.report_flags = s.get("reports", {})
    return runs


def controls_recipe(s: dict, method: str) -> list[Run]:
    """One evaluation-only run per Exp 1/2 family and seed, of that seed's CONTROLS[method] run's checkpoint."""
    runs = []
    for seed in s["seeds"]:
        for family in s["exp12_families"]:
            trained = Run(CONTROLS[method], family, s["exp12_size"], s["exp12_rank"], seed)
            runs.append(
                Run(
                    method,
                    family,
                    trained.size,
                    trained.rank,
                    seed,
                    s["controls"] + s.get("controls_family", {}).get(family, []),
                    needs=trained.name,
                )
            )
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
    """All runs of the experiments, each distinct run once (shared runs list every experiment), seed-major across
    the experiments (a sweep cut short holds every experiment at n seeds before any at n + 1); runs that need
    another run's checkpoint last."""
    unique: dict[str, Run] = {}
    for experiment in experiments:
        for run in recipe(experiment, scale):
            if run.name in unique:
                unique[run.name].experiments.append(experiment)
            else:
                unique[run.name] = run
    return sorted(unique.values(), key=lambda run: (run.needs is not None, run.seed))  # stable: the recipes' order otherwise


def read_status(run_dir: str) -> dict:
    path = os.path.join(run_dir, "run.json")
    if not os.path.isfile(path):
        return {}
    try:
        return read_json(path)
    except DamagedRun as error:  # treated as unfinished: the run resumes from its checkpoint, or starts anew
        print(f"warning: {error}; treating the run as unfinished")
        return {}


def write_status(run_dir: str, run: Run, command: list[str], status: str, **extra):
    os.makedirs(run_dir, exist_ok=True)
    record = {
        "method": run.method,
        "family": run.family,
        "size": run.size,
        "rank": run.rank,
        "seed": run.seed,
        "experiments": run.experiments,
        "command": shlex.join(command),
        "status": status,
        **extra,
    }
    with open(os.path.join(run_dir, "run.json.tmp"), "w") as f:
        json.dump(record, f, indent=1)
    os.replace(os.path.join(run_dir, "run.json.tmp"), os.path.join(run_dir, "run.json"))


def lock_run(run_dir: str, wait_s: float = 0.0) -> int | None:
    """A descriptor holding the run's exclusive lock, or None while another live process holds it.

    flock locks belong to the open file, so the kernel drops them when every process holding the
    descriptor is gone, however it died: a lock never goes stale. The script inherits the descriptor,
    so a script that outlives its launcher still holds the lock.
    """
    os.makedirs(run_dir, exist_ok=True)
    fd = os.open(os.path.join(run_dir, LOCK), os.O_RDWR | os.O_CREAT, 0o644)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
        except BlockingIOError:
            if time.monotonic() >= deadline:
                os.close(fd)
                return None
            time.sleep(min(1.0, wait_s))


def run_is_live(run_dir: str) -> bool:
    """Whether a live process holds the run's lock (the run is running now)."""
    if not os.path.isfile(os.path.join(run_dir, LOCK)):
        return False
    fd = lock_run(run_dir)
    if fd is None:
        return True
    os.close(fd)
    return False


def progress_stamp(run_dir: str) -> tuple:
    """When each of the run's progress files (checkpoint, evaluation or controls progress: *.pt) was last replaced."""
    try:
        names = sorted(n for n in os.listdir(run_dir) if n.endswith(".pt"))
    except FileNotFoundError:
        return ()
    stamps = []
    for name in names:
        try:
            stamps.append((name, os.stat(os.path.join(run_dir, name)).st_mtime_ns))
        except FileNotFoundError:  # replaced meanwhile
            pass
    return tuple(stamps)


def resume_args(run_dir: str, method: str | None = None) -> list[str]:
    """--resume from the run's checkpoint; without one, a training script starts over (--overwrite: a run that died
    before its first checkpoint left TensorBoard events, which the scripts refuse to mix with a new run's)."""
    checkpoint = os.path.join(run_dir, "checkpoint.pt")
    if os.path.isfile(checkpoint):
        return ["--resume", checkpoint]
    return [] if method in CONTROLS else ["--overwrite"]


def recorded_command(record: dict) -> list[str]:
    """The recorded command without its interpreter and --resume: what the recipe decides."""
    words = shlex.split(record.get("command", ""))[1:]
    if "--resume" in words:
        at = words.index("--resume")
        del words[at : at + 2]
    return words


_STOP = threading.Event()  # set when a local sweep is interrupted: no new runs, and runs end as "interrupted"


def measure_checkpoint(run_dir: str, method: str, env: dict, flags: dict | None = None) -> None:
    """The CHECKPOINT_REPORTS of a finished run (seconds to a few minutes each); a failure is a warning: the run is
    done all the same, and `python diagnostics/<script> CHECKPOINT > REPORT` can redo it while the checkpoint exists."""
    for report, (script, methods) in CHECKPOINT_REPORTS.items():
        if method not in methods:
            continue
        path = os.path.join(run_dir, report)
        command = [sys.executable, os.path.join(REPO, "diagnostics", script), os.path.join(run_dir, "checkpoint.pt")]
        command += (flags or {}).get(report, [])
        with open(os.path.join(run_dir, "stdout.log"), "a") as log, open(path + ".partial", "w") as out:
            returncode = subprocess.run(
                command, cwd=REPO, env={**os.environ, **env, "OMP_NUM_THREADS": "1"}, stdout=out, stderr=log
            ).returncode
        if returncode == 0:
            os.replace(path + ".partial", path)  # a report exists only whole
        else:
            os.remove(path + ".partial")
            print(f"warning: {script} failed on {run_dir} (exit {returncode}; see its stdout.log)", flush=True)


class RunJob(submitit.helpers.Checkpointable):
    """Runs one sweep run, holding its lock; the same callable for the local and the SLURM engine.

    Returns the run's final status, or "busy" when another live process owns the run.
    """

    CARRY_POLL_S = 30.0  # how often a live run's progress files are looked at for --carry

    def __init__(self, die_with_launcher: bool = False, archive: str | None = None, carry: str | None = None):
        self.process = None
        self.archive = archive  # where a finished run's measurements are copied (experiments/archive.py), or None
        self.carry = carry  # where an unfinished run's directory is copied as it saves progress, or None
        # local runs end with their launcher (SIGTERM on its death, via setpriv where it exists), as a
        # run that outlived it would finish unrecorded; SLURM ends a job's processes itself
        self.prefix = ["setpriv", "--pdeathsig", "TERM"] if die_with_launcher and shutil.which("setpriv") else []

    def __call__(self, run: Run, run_dir: str, env: dict, cuda: bool = False, lock_wait_s: float = 0.0) -> str:
        fd = lock_run(run_dir, lock_wait_s)
        if fd is None:
            return "busy"
        try:
            if read_status(run_dir).get("status") == "done":  # finished by another launcher's job meanwhile
                return "done"
            if _STOP.is_set():
                return "interrupted"
            command = run.command(run_dir, cuda)
            resume = resume_args(run_dir, run.method)
            slurm_job = os.environ.get("SLURM_ARRAY_JOB_ID", os.environ.get("SLURM_JOB_ID"))
            if slurm_job and "SLURM_ARRAY_TASK_ID" in os.environ:
                slurm_job += "_" + os.environ["SLURM_ARRAY_TASK_ID"]
            where = {"host": socket.gethostname(), **({"slurm_job": slurm_job} if slurm_job else {})}
            write_status(run_dir, run, command, "running", resumed="--resume" in resume, **where)
            start = time.time()
            with open(os.path.join(run_dir, "stdout.log"), "a") as log:
                # pass_fds: the script shares the lock (see lock_run)
                self.process = subprocess.Popen(
                    self.prefix + command + resume,
                    cwd=REPO,
                    env={**os.environ, **env},
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    pass_fds=(fd,),
                )
                carried, next_look = progress_stamp(run_dir), time.monotonic() + self.CARRY_POLL_S
                try:
                    # poll, not wait(): submitit's requeue handler runs checkpoint() -> stop() on this
                    # thread, and a nested wait() would block on the lock the outer wait() holds
                    while (returncode := self.process.poll()) is None:
                        time.sleep(0.5)
                        if self.carry and time.monotonic() > next_look:
                            next_look = time.monotonic() + self.CARRY_POLL_S
                            if (stamp := progress_stamp(run_dir)) != carried:
                                carried = stamp
                                self.carry_progress(run_dir)
                except BaseException:  # SLURM requeue (SystemExit from submitit's signal handler) or Ctrl-C
                    self.stop()
                    raise
            # a script ended by SIGTERM/SIGINT was stopped from outside (a shutdown signals the scripts and the
            # launcher together, so _STOP may not be set yet): it resumes from its checkpoint, it did not fail
            stopped = _STOP.is_set() or returncode in (
                -signal.SIGTERM,
                -signal.SIGINT,
                128 + signal.SIGTERM,
                128 + signal.SIGINT,
            )
            status = "interrupted" if stopped else "done" if returncode == 0 else "failed"
            if status == "done":
                measure_checkpoint(run_dir, run.method, env, run.report_flags)
            write_status(
                run_dir,
                run,
                command,
                status,
                resumed="--resume" in resume,
                returncode=returncode,
                seconds=round(time.time() - start, 1),
                **where,
            )
            if status == "done" and self.archive:
                try:
                    archive_run(run_dir, self.archive)
                    if self.carry:  # archived: its carried copy has served
                        shutil.rmtree(os.path.join(self.carry, run.name), ignore_errors=True)
                except (OSError, ValueError) as error:  # the run is done all the same; experiments/archive.py can redo this
                    print(f"warning: {run.name} not archived: {error}", flush=True)
            elif self.carry and progress_stamp(run_dir):
                self.carry_progress(run_dir)
            return status
        finally:
            os.close(fd)

    def carry_progress(self, run_dir: str) -> None:
        try:
            carry_run(run_dir, self.carry)
        except OSError as error:  # the run goes on; the next progress file tries again
            print(f"warning: {os.path.basename(run_dir)} not carried: {error}", flush=True)

    def stop(self, grace_s: float = 30.0):
        """Ends the script (SIGTERM, then SIGKILL), with bounded waits: it resumes from its last checkpoint."""
        process = self.process
        if process is None:
            return
        for send, wait_s in ((process.terminate, grace_s), (process.kill, 10.0)):
            if process.poll() is not None:
                return
            send()
            deadline = time.monotonic() + wait_s
            while process.poll() is None and time.monotonic() < deadline:
                time.sleep(0.2)

    def checkpoint(self, run: Run, run_dir: str, env: dict, cuda: bool = False, lock_wait_s: float = 0.0):
        """submitit calls this on preemption or time-out, then requeues the returned submission.

        The script checkpoints every --checkpoint-every steps on its own; the requeued job finds that
        checkpoint and passes --resume.
        """
        self.stop()
        record = read_status(run_dir)
        if record.get("status") == "running":
            write_status(
                run_dir,
                run,
                run.command(run_dir, cuda),
                "requeued",
                **{k: record[k] for k in ("slurm_job", "host") if k in record},
            )
        return submitit.helpers.DelayedSubmission(
            RunJob(archive=self.archive, carry=self.carry), run, run_dir, env, cuda, lock_wait_s
        )


def slurm_queued(job_id: str | None) -> bool:
    """Whether SLURM still lists the job (pending or running); False where squeue is absent."""
    if not job_id or shutil.which("squeue") is None:
        return False
    try:
        listed = subprocess.run(["squeue", "-h", "-o", "%i", "-j", job_id], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return True  # a busy controller: better to skip a run than to double it
    return listed.returncode == 0 and bool(listed.stdout.strip())


def pending_runs(runs: list[Run], root: str, cuda: bool = False, archive: str | None = None) -> list[tuple[Run, str]]:
    """The runs to start now, printing why each other run is skipped."""
    pending = []
    for run in runs:
        run_dir = os.path.join(root, run.name)
        if is_archived(archive, run.name):
            print(f"skip (archived) {run.name}")
            continue
        command = run.command(run_dir, cuda)
        record = read_status(run_dir)
        if record and recorded_command(record) != command[1:]:  # the interpreter may differ between machines
            print(
                f"changed      {run.name}: the recipe's command differs from the recorded one (run.json);"
                f" delete the run directory to rerun it\n  recorded {record.get('command')}\n  recipe   {shlex.join(command)}"
            )
        if record.get("status") == "done":
            print(f"skip (done)  {run.name}")
            continue
        if run_is_live(run_dir):
            print(f"skip (running) {run.name}")
            continue
        if record.get("status") in ("queued", "requeued") and slurm_queued(record.get("slurm_job")):
            print(f"skip (queued {record['slurm_job']}) {run.name}")
            continue
        if run.needs and read_status(os.path.join(root, run.needs)).get("status") != "done":
            lost = (
                " (archived without its weights: delete it from the archive to retrain it)"
                if is_archived(archive, run.needs)
                else ""
            )
            print(f"wait (needs {run.needs} done){lost} {run.name}")
            continue
        resume = resume_args(run_dir, run.method)
        print(("resume " if "--resume" in resume else "run    ") + shlex.join(command + resume))
        pending.append((run, run_dir, "--resume" in resume))
    # evaluation-only runs whose checkpoint is ready start first: short, and they say whether the trained runs use
    # their context while the long queue goes on; then interrupted runs, so that a restart finishes what it cut
    # before it opens new runs (stable: the recipes' order otherwise)
    pending.sort(key=lambda item: (item[0].needs is None, not item[2]))
    return [(run, run_dir) for run, run_dir, _ in pending]


def local_threads(root: str, workers: int) -> str:
    """Threads per run: this machine's cores shared by this launcher's workers and the runs already live in root.

    A run another launcher started keeps the threads it was given (at least one, counted as one), and a
    launcher cannot lower them: two launchers of one worker each on 2 cores gave each run 2 threads, 0.4-0.6
    agent steps/s against 12-15 with one thread each (size F, Reach). Counting the live runs lessens that
    oversubscription; OMP_NUM_THREADS=1 for both launchers removes it.
    """
    live = [name for name in sorted(os.listdir(root)) if run_is_live(os.path.join(root, name))] if os.path.isdir(root) else []
    if live:
        print(f"note: {len(live)} run(s) of another launcher live in {root} ({', '.join(live)}): sharing the cores with them")
    return str(max(1, ((os.cpu_count() or 1) - len(live)) // workers))


def restore_runs(runs: list[Run], root: str, archive: str | None, carry: str | None, dry_run: bool) -> None:
    """Into a sweep directory that lacks them: the carried copies of unfinished runs (to resume), and the archived
    weights of the finished runs that a run still to do needs (Run.needs)."""
    sources = [os.path.join(carry, run.name) for run in runs if carry and not is_archived(archive, run.name)]
    sources += [
        os.path.join(archive, run.needs)
        for run in runs
        if archive
        and run.needs
        and not is_archived(archive, run.name)
        and is_archived(archive, run.needs)
        and os.path.isfile(os.path.join(archive, run.needs, WEIGHTS))
    ]
    for source in dict.fromkeys(sources):  # once each, in order
        if os.path.isdir(source) and not os.path.exists(os.path.join(root, os.path.basename(source))):
            if dry_run:
                print(f"would restore {source}")
            elif restore_run(source, root):
                print(f"restored     {source} -> {root}")


def launch(
    runs: list[Run],
    root: str,
    workers: int | None,
    dry_run: bool,
    launcher: str = "local",
    slurm: dict | None = None,
    archive: str | None = None,
    carry: str | None = None,
) -> int:
    """Run (local) or submit (slurm) every run not finished nor live nor archived; returns the number that failed."""
    slurm = slurm or {}
    cuda = slurm.get("gpus_per_task", 0) > 0
    restore_runs(runs, root, archive, carry, dry_run)
    pending = pending_runs(runs, root, cuda, archive)
    if dry_run or not pending:
        return 0
    # small networks: cores/workers BLAS/OpenMP threads per run, or parallel runs thrash each
    # other's threads; an OMP_NUM_THREADS already set (e.g. beside another sweep) wins
    if launcher == "slurm":
        threads = os.environ.get("OMP_NUM_THREADS") or str(slurm.get("cpus_per_task", 1))
    else:
        threads = os.environ.get("OMP_NUM_THREADS") or local_threads(root, workers or 1)
        print(f"local: {workers or 1} run(s) at a time, OMP_NUM_THREADS={threads} each")
    env = {"OMP_NUM_THREADS": threads, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "disable")}
    if launcher == "slurm":
        return submit_slurm(pending, root, env, cuda, workers, slurm, archive, carry)
    started = {run.name for run, _ in pending}
    waiting = [
        (run, os.path.join(root, run.name))
        for run in runs
        if run.needs
        and run.name not in started
        and read_status(os.path.join(root, run.name)).get("status") != "done"
        and not is_archived(archive, run.name)
    ]
    return run_local(pending, env, workers or 1, waiting, archive, carry)


def run_local(
    pending: list[tuple[Run, str]],
    env: dict,
    workers: int,
    waiting: list[tuple[Run, str]] = (),
    archive: str | None = None,
    carry: str | None = None,
) -> int:
    """Runs on this machine, `workers` at a time; a waiting run (Run.needs) joins the front of the queue as soon
    as the run it needs is done, so one launcher call runs the evaluations of the checkpoints it trains.

    Threads over RunJob rather than submitit's LocalExecutor: that one starts every job at once (no
    cap on parallel runs) and kills each after its timeout_min; DebugExecutor runs one at a time.
    The threads only wait on their scripts' processes.
    """
    queue, waiting, running = list(pending), list(waiting), {}
    _STOP.clear()

    def interrupt(signum, frame):  # end the scripts too, so that no run outlives its launcher unrecorded
        _STOP.set()
        for _, job in list(running.values()):
            if job.process is not None and job.process.poll() is None:
                job.process.terminate()

    handlers = {}
    if threading.current_thread() is threading.main_thread():
        handlers = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    failed, start = 0, time.time()
    try:
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            while running or (queue and not _STOP.is_set()):
                while queue and len(running) < workers and not _STOP.is_set():
                    run, run_dir = queue.pop(0)
                    job = RunJob(die_with_launcher=True, archive=archive, carry=carry)
                    running[pool.submit(job, run, run_dir, env)] = (run, job)
                done, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in done:
                    run, _ = running.pop(future)
                    status = future.result()
                    failed += status == "failed"
                    label = "skip (running)" if status == "busy" else f"{status:6s}"
                    print(f"{label} {run.name} ({time.time() - start:.0f} s into the sweep)", flush=True)
                ready = [
                    item
                    for item in waiting
                    if read_status(os.path.join(os.path.dirname(item[1]), item[0].needs)).get("status") == "done"
                ]
                for run, _ in ready:
                    print(f"ready        {run.name} ({run.needs} is done)", flush=True)
                waiting = [item for item in waiting if item not in ready]
                queue[:0] = ready
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    if _STOP.is_set():
        raise SystemExit("interrupted: rerun the same command to resume the unfinished runs")
    return failed


def submit_slurm(
    pending: list[tuple[Run, str]],
    root: str,
    env: dict,
    cuda: bool,
    workers: int | None,
    slurm: dict,
    archive: str | None = None,
    carry: str | None = None,
) -> int:
    """Submits the runs as one SLURM job array and returns; each array task runs RunJob on its node."""
    executor = submitit.SlurmExecutor(
        folder=os.path.join(root, ".submitit", "%j"), max_num_timeout=slurm.get("max_requeues", 3)
    )
    parameters = {
        "job_name": "claw-sweep",
        "time": slurm.get("time", 60),
        "cpus_per_task": slurm.get("cpus_per_task", 1),
        "stderr_to_stdout": True,
        # the nodes unpickle RunJob from experiments.sweep
        "setup": [f"export PYTHONPATH={shlex.quote(REPO)}${{PYTHONPATH:+:$PYTHONPATH}}"],
        "additional_parameters": slurm.get("sbatch", {}),
    }
    for key in ("partition", "gpus_per_task"):
        if slurm.get(key):
            parameters[key] = slurm[key]
    if workers:
        parameters["array_parallelism"] = workers
    executor.update_parameters(**parameters)
    runs, run_dirs = zip(*pending)
    # a requeued job may start while the killed one's processes are still being reaped: wait for its lock
    jobs = executor.map_array(
        RunJob(archive=archive, carry=carry), runs, run_dirs, [env] * len(runs), [cuda] * len(runs), [120.0] * len(runs)
    )
    for (run, run_dir), job in zip(pending, jobs):
        write_status(run_dir, run, run.command(run_dir, cuda), "queued", slurm_job=job.job_id, slurm_log=str(job.paths.stdout))
    print(
        f"submitted {len(jobs)} runs as SLURM job array {jobs[0].job_id.split('_')[0]}; follow with squeue, rerun "
        f"this command to resubmit runs that died, aggregate once squeue lists none",
        flush=True,
    )
    return 0


def parse_minutes(text: str) -> int:
    """SLURM time limit as minutes: MINUTES, HH:MM:SS or D-HH:MM[:SS]."""
    days, _, clock = text.rpartition("-")
    parts = [int(p) for p in clock.split(":")]
    if not 1 <= len(parts) <= 3 or (len(parts) == 1 and days) or any(p < 0 for p in parts):
        raise ValueError(text)
    if len(parts) == 1:
        minutes = parts[0]
    else:
        hours, mins, secs = (parts + [0])[:3]
        minutes = hours * 60 + mins + (secs > 0)
    return int(days or 0) * 1440 + minutes


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "experiments", nargs="+", choices=["budget", "controls", "decoder", "exp1", "exp2", "exp3", "exp4", "exp5"]
    )
    parser.add_argument("--scale", choices=list(SCALES), default="paper")
    parser.add_argument(
        "--launcher",
        choices=["local", "slurm"],
        default="local",
        help="local: runs on this machine; slurm: submits a job array and returns",
    )
    parser.add_argument(
        "--workers", type=int, default=None, help="parallel runs (local: default 1; slurm: array parallelism, default no cap)"
    )
    parser.add_argument("--root", default=None, help="sweep directory (default runs/sweeps/{scale})")
    parser.add_argument("--methods", nargs="+", choices=list(SCRIPTS), default=None, help="only these methods' runs")
    parser.add_argument(
        "--families",
        nargs="+",
        default=None,
        metavar="FAMILY",
        help="only these families' runs (as run names spell them: reach, walker, cheetah_walker, ...)",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=None, metavar="SEED", help="only these seeds' runs")
    parser.add_argument(
        "--archive",
        default=None,
        metavar="DIR",
        help="copy each finished run's measurements and weights (not its replay buffer) to DIR, e.g. results/learn/runs, and skip"
        " the runs DIR holds: commit DIR, and a sweep directory lost with its machine loses no finished run"
        " (experiments/archive.py)",
    )
    parser.add_argument(
        "--carry",
        default=None,
        metavar="DIR",
        help="copy each unfinished run's directory to DIR, e.g. results/learn/carry, whenever it saves progress,"
        " and restore from DIR the runs the sweep directory lacks: commit DIR, and a run outlives its"
        " machine (resumed from its last checkpoint by the next launcher); needs --archive",
    )
    parser.add_argument("--dry-run", action="store_true", help="list the commands and exit")
    group = parser.add_argument_group("slurm", "options of --launcher slurm")
    group.add_argument("--partition", default=None)
    group.add_argument(
        "--time",
        default=None,
        help="time limit per run: MINUTES, HH:MM:SS or D-HH:MM (default 60);"
        " a run that hits it is requeued and resumes from its checkpoint",
    )
    group.add_argument("--cpus-per-task", type=int, default=None, help="default 1; also the runs' OMP_NUM_THREADS")
    group.add_argument("--gpus-per-task", type=int, default=None, help="default 0; >0 runs the scripts on CUDA")
    group.add_argument("--max-requeues", type=int, default=None, help="time-outs before a run gives up (default 3)")
    group.add_argument(
        "--sbatch",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other sbatch option, e.g. --sbatch qos=high --sbatch account=lab (repeatable)",
    )
    cli = parser.parse_args(argv)

    def fail(message: str):  # one line, not argparse's usage block
        raise SystemExit(f"sweep.py: error: {message}")

    if cli.workers is not None and cli.workers < 1:
        fail(f"--workers must be >= 1, got {cli.workers}")
    slurm = {}
    slurm_options = {
        "partition": cli.partition,
        "time": cli.time,
        "cpus_per_task": cli.cpus_per_task,
        "gpus_per_task": cli.gpus_per_task,
        "max_requeues": cli.max_requeues,
        "sbatch": cli.sbatch,
    }
    if cli.launcher == "local":
        given = [f"--{k.replace('_', '-')}" for k, v in slurm_options.items() if v not in (None, [])]
        if given:
            fail(f"{', '.join(given)}: options of --launcher slurm only")
    else:
        if not cli.dry_run and shutil.which("sbatch") is None:
            fail("--launcher slurm needs sbatch on PATH (run it on a SLURM login node)")
        try:
            slurm["time"] = parse_minutes(cli.time) if cli.time else 60
        except ValueError:
            fail(f"--time {cli.time!r}: expected MINUTES, HH:MM:SS or D-HH:MM")
        for key in ("cpus_per_task", "gpus_per_task", "max_requeues"):
            if slurm_options[key] is not None:
                if slurm_options[key] < (1 if key == "cpus_per_task" else 0):
                    fail(f"--{key.replace('_', '-')} {slurm_options[key]} is out of range")
                slurm[key] = slurm_options[key]
        if cli.partition:
            slurm["partition"] = cli.partition
        slurm["sbatch"] = {}
        for option in cli.sbatch:
            key, sep, value = option.lstrip("-").partition("=")
            if not sep or not key or not all(c.isalnum() or c in "-_" for c in key):
                fail(f"--sbatch {option!r}: expected KEY=VALUE, e.g. qos=high")
            slurm["sbatch"][key.replace("-", "_")] = value
    root = cli.root or os.path.join("runs", "sweeps", cli.scale)
    if os.path.exists(root) and not os.path.isdir(root):
        raise SystemExit(f"error: --root {root!r} exists and is not a directory")
    planned = plan_runs(cli.experiments, cli.scale)
    for option, values, known in (
        ("--families", cli.families, {r.family for r in planned}),
        ("--seeds", cli.seeds, {r.seed for r in planned}),
    ):
        if values is not None and set(values) - known:
            fail(
                f"{option} {' '.join(map(str, sorted(set(values) - known)))}: not in these recipes (they have {' '.join(map(str, sorted(known)))})"
            )
    runs = [
        r
        for r in planned
        if (cli.methods is None or r.method in cli.methods)
        and (cli.families is None or r.family in cli.families)
        and (cli.seeds is None or r.seed in cli.seeds)
    ]
    print(f"{len(runs)} runs for {' '.join(cli.experiments)} at scale {cli.scale} in {root}")
    archive = os.path.abspath(cli.archive) if cli.archive else None
    if cli.carry and not archive:
        fail("--carry needs --archive: a carried run's copy is removed once the archive holds the run")
    carry = os.path.abspath(cli.carry) if cli.carry else None
    failed = launch(runs, os.path.abspath(root), cli.workers, cli.dry_run, cli.launcher, slurm, archive, carry)
    if failed:
        raise SystemExit(f"{failed} run(s) failed; see their stdout.log and run.json")


if __name__ == "__main__":
    # run through the package module, so that the jobs pickle RunJob as experiments.sweep.RunJob
    from experiments import sweep

    sweep.main()
