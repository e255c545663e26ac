"""Test-time adaptation protocols shared by every method script (paper Exp 1 and Exp 2).

The protocols only roll environments and time-steps; the method lives in two callables the
script passes in:
    adapt(context) -> None          # CLAW: one hypernet pass; DR/ST: gradient step(s); oracle: no-op
    act(obs, first_step) -> action  # the planner with the currently adapted weights
`context` is the dict returned by `common.context.collect_episodes` (pi_con data).
"""

from __future__ import annotations

import os
from typing import Callable

import numpy as np
from tqdm import tqdm

from common.context import collect_episodes
from common.envs import make_env

AdaptFn = Callable[[dict], None]
ActFn = Callable[[np.ndarray, bool], np.ndarray]


def progress_bar(iterable=None, total: int | None = None, desc: str = ""):
    """tqdm on stderr that leaves no line behind; silent when stderr is not a terminal (logs, sweeps)
    unless CLAW_PROGRESS=1. The scripts' prefill and burst bars use it too."""
    disable = None if os.environ.get("CLAW_PROGRESS") != "1" else False
    return tqdm(iterable, total=total, desc=desc, leave=False, dynamic_ncols=True, disable=disable, mininterval=1.0)


def online_adaptation(
    env, context: dict, adapt: AdaptFn, act: ActFn, num_steps: int, seed: int, desc: str | None = None
) -> list[dict]:
    """Exp 1: roll out for `num_steps` agent steps, re-adapting before every planner call.

    Returns one record per finished episode: the test-time step at which it ended, its return
    and its final-step success (always 0.0 outside Meta-World). desc: label of a progress bar."""
    records = []
    obs, _ = env.reset(seed=seed)
    first_step, episode_return = True, 0.0
    for step in progress_bar(range(1, num_steps + 1), desc=desc) if desc else range(1, num_steps + 1):
        adapt(context)
        action = act(obs, first_step)
        obs, reward, terminated, truncated, info = env.step(action)
        episode_return += float(reward)
        first_step = False
        if terminated or truncated:
            records.append({"step": step, "return": episode_return, "success": float(info.get("success", 0.0))})
            obs, _ = env.reset()
            first_step, episode_return = True, 0.0
    return records


def offline_adaptation(
    env,
    context: dict,
    adapt: AdaptFn,
    act: ActFn,
    num_episodes: int,
    seed: int,
    desc: str | None = None,
    video: str | bool | None = None,
) -> list[dict]:
    """Exp 2: adapt once on the fixed context data, freeze, and evaluate `num_episodes` episodes
    (desc: label of a progress bar over them). video: an .mp4 path that records the first episode (falsy: none)."""
    adapt(context)
    records = []
    for episode in progress_bar(range(num_episodes), desc=desc) if desc else range(num_episodes):
        obs, _ = env.reset(seed=seed + episode)
        first_step, episode_return, done = True, 0.0, False
        frames = [env.render()] if video and episode == 0 else None
        while not done:
            obs, reward, terminated, truncated, info = env.step(act(obs, first_step))
            episode_return += float(reward)
            first_step, done = False, terminated or truncated
            if frames is not None:
                frames.append(env.render())
        if frames is not None:
            write_video(video, frames, env.metadata["render_fps"])
        records.append({"return": episode_return, "success": float(info.get("success", 0.0))})
    return records


def write_video(path: str, frames: list, fps: int) -> None:
    """H.264 .mp4 through imageio's ffmpeg plugin (imageio-ffmpeg ships the ffmpeg binary)."""
    import imageio.v2 as imageio

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    imageio.mimwrite(path, frames, fps=fps, codec="libx264", quality=7, macro_block_size=16)


def mean_ci(values, confidence: float = 0.95) -> tuple[float, float]:
    """Mean and half-width of the Student-t confidence interval of the mean (paper: across seeds).

    A single value has no spread estimate: its half-width is NaN, not zero."""
    values = np.asarray(values, dtype=np.float64)
    mean = float(values.mean())
    if values.size < 2:
        return mean, float("nan")
    import scipy.stats  # here, not at the top: its import costs every script's start-up ~1.7 s

    sem = scipy.stats.sem(values)
    return mean, float(sem * scipy.stats.t.ppf(0.5 + confidence / 2, values.size - 1))


# ---------------------------------------------------------------------------------------------
# The Exp 1 and Exp 2 runs of a family, their scalars and printed intervals, resumable per environment
# ---------------------------------------------------------------------------------------------
def global_rng_state() -> dict:
    """Python's, NumPy's and torch's generators: restored, a resumed run draws what an uninterrupted one would."""
    import random

    import torch

    return {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
    }


def set_global_rng_state(state: dict) -> None:
    import random

    import torch

    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if state["cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def weights_digest(*modules) -> str:
    """Identifies the weights an evaluation belongs to: progress saved for other weights is not taken up."""
    import hashlib

    digest = hashlib.sha256()
    for module in modules:
        for tensor in module.state_dict().values():
            digest.update(tensor.detach().cpu().numpy().tobytes())
    return digest.hexdigest()


def save_evaluation_progress(path: str, results: dict, weights: str) -> None:
    """After each environment: an evaluation killed later goes on from the next one (walker's take minutes each)."""
    import torch

    try:
        torch.save({"results": results, "rng": global_rng_state(), "weights": weights}, path + ".tmp")
    except (OSError, RuntimeError) as error:  # a full disk: OSError, or RuntimeError ("unexpected pos") from the zip writer
        if os.path.exists(path + ".tmp"):
            os.remove(path + ".tmp")
        kept = "; the previous one is intact" if os.path.exists(path) else ""
        raise SystemExit(
            f"error: cannot write {path} ({str(error).splitlines()[0] if str(error) else type(error).__name__}){kept}"
        ) from None
    os.replace(path + ".tmp", path)


def load_evaluation_progress(path: str, weights: str) -> dict:
    import torch

    progress = torch.load(path, map_location="cpu", weights_only=False)
    if progress["weights"] != weights:
        print(f"ignoring {path}: saved by an evaluation of other weights", flush=True)
        return {"online": {}, "offline": {}}
    set_global_rng_state(progress["rng"])
    print(f"resumed the evaluation from {path}: {len(progress['results']['online'])} environments done", flush=True)
    return progress["results"]


def evaluate_family(
    env_ids,
    adapt: AdaptFn,
    act: ActFn,
    writer,
    args,
    *,
    online_adapt: AdaptFn | None = None,
    reset: AdaptFn | None = None,
    offline_points=None,
    env_kwargs: dict | None = None,
    progress_path: str | None = None,
    weights: str = "",
    after_each_env: Callable[[], None] | None = None,
) -> dict:
    """Exp 1 and Exp 2 on every environment of env_ids, with a script's adapt and act.

    Environment env_id of args.family (built with env_kwargs, e.g. the Oracle's oracle=True) gets a fresh pi_con
    context of args.context_episodes episodes; the seeds of both depend on args.seed and env_id only. Exp 1
    re-adapts with online_adapt (default adapt) before every planner call. Exp 2 adapts once with adapt(context),
    or, given offline_points (the DR/ST/Oracle sweep), once per point with adapt(context, steps), after reset(context).
    Per-environment and family scalars go to writer, the family's 95% t-CI across environments is printed; with
    progress_path the results are saved after each environment (weights: the digest of the evaluated weights) and an
    interrupted evaluation resumes from the next one; after_each_env() runs once an environment's results are saved
    (the scripts stop there on SIGINT/SIGTERM). Returns {"online": {env: records}, "offline": {env: records, or
    {steps: records} with a sweep}}."""
    reset = reset or (lambda context: None)
    sweep = offline_points is not None
    results = {"online": {}, "offline": {}}
    if progress_path and os.path.exists(progress_path):  # an interrupted evaluation: skip the environments it finished
        results = load_evaluation_progress(progress_path, weights)
    for env_id in list(env_ids)[len(results["online"]) :]:
        env = make_env(args.family, env_id, **(env_kwargs or {}), seed=args.seed + 10_000 + env_id)
        context = collect_episodes(env, args.context_episodes, seed=args.seed + 20_000 + env_id)
        reset(context)
        online = online_adaptation(
            env,
            context,
            online_adapt or adapt,
            act,
            args.online_eval_steps,
            seed=args.seed + 30_000 + env_id,
            desc=f"eval env {env_id} online",
        )
        for record in online:
            writer.add_scalar(f"eval/online/env{env_id}/episodic_return", record["return"], record["step"])
            writer.add_scalar(f"eval/online/env{env_id}/success", record["success"], record["step"])
        results["online"][env_id] = online
        offline_by_steps = {}
        for steps in offline_points if sweep else (0,):  # no sweep: one adaptation, logged at step 0
            reset(context) if sweep else None
            video = (
                args.capture_video and f"{writer.log_dir}/videos/env{env_id}_offline{f'_{steps}steps' if sweep else ''}.mp4"
            )
            offline = offline_adaptation(
                env,
                context,
                (lambda c, n=steps: adapt(c, n)) if sweep else adapt,
                act,
                args.eval_episodes,
                seed=args.seed + 40_000 + env_id,
                desc=f"eval env {env_id} offline",
                video=video,
            )
            writer.add_scalar(
                f"eval/offline/env{env_id}/episodic_return", float(np.mean([r["return"] for r in offline])), steps
            )
            writer.add_scalar(f"eval/offline/env{env_id}/success", float(np.mean([r["success"] for r in offline])), steps)
            offline_by_steps[steps] = offline
        results["offline"][env_id] = offline_by_steps if sweep else offline_by_steps[0]
        if sweep:
            offline_text = ", ".join(
                f"{np.mean([r['return'] for r in recs]):.1f} ({n} steps)" for n, recs in offline_by_steps.items()
            )
        else:
            offline_text = f"{np.mean([r['return'] for r in offline_by_steps[0]]):.1f}"
        print(
            f"eval env {env_id}: online last-episode return {online[-1]['return'] if online else float('nan'):.1f}, "
            f"offline return {offline_text}",
            flush=True,
        )
        if progress_path:
            save_evaluation_progress(progress_path, results, weights)
        if after_each_env:
            after_each_env()
    # family averages: every environment has episodes of equal length, so episode k ends at the same step
    first = next(iter(results["online"]))
    for k in range(min(len(r) for r in results["online"].values())):
        step = results["online"][first][k]["step"]
        for key in ("return", "success"):
            value = np.mean([results["online"][e][k][key] for e in results["online"]])
            writer.add_scalar(f"eval/online/{'episodic_return' if key == 'return' else key}", value, step)
    for steps in offline_points if sweep else (0,):
        per_env = [recs[steps] if sweep else recs for recs in results["offline"].values()]
        mean, ci = mean_ci([np.mean([r["return"] for r in recs]) for recs in per_env])
        writer.add_scalar("eval/offline/episodic_return", mean, steps)
        writer.add_scalar("eval/offline/success", np.mean([r["success"] for recs in per_env for r in recs]), steps)
        label = f" ({steps} steps)" if sweep else ""
        print(f"eval offline{label}: return {mean:.1f} +- {ci:.1f} (95% t-CI across environments)", flush=True)
    writer.flush()
    if progress_path and os.path.exists(progress_path):  # complete: another evaluation of these weights starts afresh
        os.remove(progress_path)
    return results
