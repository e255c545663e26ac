"""Run plumbing shared by every method script: argument checks, checked checkpoints, progress.

Kept out of the scripts so that each of them stays a readable copy of the others: a script calls
these helpers with the same lines, and `diff` between two scripts still shows only the method.
"""
from __future__ import annotations

import math
import os
import subprocess
import time

import torch
from tqdm import tqdm

from common.envs import episode_length, is_metaworld, num_envs

# flags that cannot change a run's results: --resume takes them anew if given, else from the checkpoint
RESUME_FREE = ("threads", "cuda", "log_every", "checkpoint_every", "checkpoint_minutes")
NOT_SAVED = ("run_dir", "resume", "checkpoint", "eval_only", "dry_run")  # this invocation's own


def flag(key: str) -> str:
    return "--" + key.replace("_", "-")


def check_counts(args, positive: tuple[str, ...], nonnegative: tuple[str, ...] = ()):
    """One error line for the first count out of range, before any work; keys a script lacks are skipped."""
    for key in positive:
        value = getattr(args, key, None)
        if value is not None and value <= 0:
            raise SystemExit(f"error: {flag(key)} must be a positive {'number' if isinstance(value, float) else 'integer'}, got {value}")
    for key in nonnegative:
        value = getattr(args, key, None)
        if value is not None and value < 0:
            raise SystemExit(f"error: {flag(key)} must be >= 0, got {value}")


def prefill_steps(seed_steps: int, n_envs: int, ep_len: int, envs_filled: int) -> int:
    """Random-action prefill in agent steps: whole episodes, seed_steps spread over n_envs
    environments (at least one episode each), of which envs_filled are actually rolled."""
    return max(1, math.ceil(seed_steps / (n_envs * ep_len))) * envs_filled * ep_len


def resolve_budget(args, default_total: dict, n_envs: int | None = None, envs_filled: int | None = None) -> tuple[int, int, int]:
    """(total agent steps, --seed-steps, prefill agent steps) with the paper's defaults filled in.
    n_envs: environments the prefill is spread over (default the family's); envs_filled: of them rolled (default all)."""
    ep_len = episode_length(args.family)
    n_envs = num_envs(args.family) if n_envs is None else n_envs
    total = args.total_timesteps if args.total_timesteps is not None else default_total[args.family]
    seed_steps = args.seed_steps if args.seed_steps is not None else max(1000, 5 * ep_len)
    return total, seed_steps, prefill_steps(seed_steps, n_envs, ep_len, n_envs if envs_filled is None else envs_filled)


def check_budget(budget: int, prefill: int, what: str = "--total-timesteps"):
    if budget <= prefill:
        raise SystemExit(f"error: {what}: {budget} must exceed the random-action prefill of {prefill} steps "
                         "(whole episodes, at least one per environment); raise it or lower --seed-steps")


def read_checkpoint(path: str, method: str, model=None) -> dict:
    """torch.load with one error line for an unreadable file, another script's checkpoint, or (given
    the model it is loaded into) another family, model size or observation/action dimension."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # truncated, corrupt or not a torch file: torch raises many types
        detail = f"{type(error).__name__}: {str(error).splitlines()[0]}" if str(error) else type(error).__name__
        raise SystemExit(f"error: cannot read checkpoint {path} (truncated, corrupt or not a torch file): {detail}") from None
    if not isinstance(state, dict) or not isinstance(state.get("args"), dict) or "model" not in state:
        raise SystemExit(f"error: {path} is not a checkpoint of these scripts (no saved 'args' and 'model')")
    found = state.get("method", f"{state['args'].get('exp_name')}.py")  # older checkpoints: the run's exp_name
    if found != method:
        raise SystemExit(f"error: {path} is a {found} checkpoint, expected one written by {method}")
    if model is not None:
        expected = {"family": model.args.family, "model_size": model.args.model_size, "dims": (model.obs_dim, model.act_dim)}
        found = {**state["args"], "dims": tuple(state.get("dims", expected["dims"]))}
        for key, value in expected.items():
            if found.get(key, value) != value:
                raise SystemExit(f"error: {path} holds {key} {found[key]}, expected {value}")
    return state


def mismatch(error: Exception) -> str:
    """The first informative line of a load_state_dict error (which lists every tensor)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return next((line for line in lines if "size mismatch" in line or "Missing" in line or "Unexpected" in line), lines[0] if lines else "")


def adopt_args(args, saved: dict, keys, path: str):
    """Set args.key = saved[key] for keys (None: every saved argument). A flag given explicitly (it
    differs from the dataclass default) with another value than the saved one is an error, except
    the RESUME_FREE ones, which keep the given value."""
    defaults = type(args)()
    for key in [k for k in saved if k not in NOT_SAVED] if keys is None else keys:
        if key not in saved or not hasattr(args, key):
            continue
        given = getattr(args, key)
        if given != getattr(defaults, key) and given != saved[key]:
            if key in RESUME_FREE:
                continue
            raise SystemExit(f"error: {flag(key)} {given} conflicts with {saved[key]} in {path}; leave it out to use the checkpoint's")
        setattr(args, key, saved[key])


def describe_device(args, device: torch.device, model_size: str) -> str:
    """Start-up lines: the device, a warning when CUDA was asked for but is missing, a size hint."""
    lines = [f"device: {device}"]
    if args.cuda and device.type == "cpu":
        lines.append("warning: --cuda was asked for but CUDA is not available; running on the CPU (slow; --no-cuda silences this)")
    if device.type == "cpu" and model_size in ("A", "B"):
        lines.append(f"hint: model size {model_size} is slow on a CPU; --model-size F trains in a fraction of the time")
    return "\n".join(lines)


def git_commit() -> str:
    try:
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def hyperparameter_text(args, **resolved) -> str:
    """The TensorBoard hyperparameter table with resolved values (no None for a default)."""
    values = {**vars(args), **resolved, "git_commit": git_commit()}
    return "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in values.items())


def hms(seconds: float) -> str:
    seconds = int(max(0, seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def progress_text(step: int, total: int, start_step: int, start_time: float, started: float, recent, family: str) -> str:
    """'return R | success S | SPS n | elapsed h:mm:ss | ETA h:mm:ss': mean of the recent (return, success)
    episodes, agent steps per second since start_time (at start_step), elapsed since started."""
    now = time.time()
    rate = (step - start_step) / max(now - start_time, 1e-9)
    parts = [f"return {sum(r for r, _ in recent) / len(recent):.1f}" if recent else "return -"]
    if is_metaworld(family):
        parts.append(f"success {sum(s for _, s in recent) / len(recent):.2f}" if recent else "success -")
    eta = hms((total - step) / rate) if rate > 0 else "-"
    return " | ".join(parts + [f"SPS {int(rate)}", f"elapsed {hms(now - started)}", f"ETA {eta}"])


def progress_bar(iterable=None, total: int | None = None, desc: str = ""):
    """tqdm on stderr that leaves no line behind; silent when stderr is not a terminal (logs, sweeps)
    unless CLAW_PROGRESS=1."""
    disable = None if os.environ.get("CLAW_PROGRESS") != "1" else False
    return tqdm(iterable, total=total, desc=desc, leave=False, dynamic_ncols=True, disable=disable, mininterval=1.0)


def random_prefill(envs: dict, replay, total: int) -> int:
    """Random-action prefill of `total` agent steps, split evenly over the environments ({replay slice:
    env}) in whole episodes, with a progress bar; returns the agent steps taken."""
    steps, bar = 0, progress_bar(total=total, desc="prefill")
    for env_id, env in envs.items():
        env_steps = 0
        while env_steps < total // len(envs):
            obs, _ = env.reset()
            done, first = False, True
            while not done:
                action = env.action_space.sample()
                next_obs, reward, terminated, truncated, _ = env.step(action)
                replay.add(env_id, obs, action, reward, next_obs, first)
                obs, first, done, env_steps = next_obs, False, terminated or truncated, env_steps + 1
                bar.update()
        steps += env_steps
    bar.close()
    return steps
