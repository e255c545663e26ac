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
import scipy.stats
from tqdm import tqdm

AdaptFn = Callable[[dict], None]
ActFn = Callable[[np.ndarray, bool], np.ndarray]


def progress_bar(iterable=None, total: int | None = None, desc: str = ""):
    """tqdm on stderr that leaves no line behind; silent when stderr is not a terminal (logs, sweeps)
    unless CLAW_PROGRESS=1. The scripts' prefill and burst bars use it too."""
    disable = None if os.environ.get("CLAW_PROGRESS") != "1" else False
    return tqdm(iterable, total=total, desc=desc, leave=False, dynamic_ncols=True, disable=disable, mininterval=1.0)


def online_adaptation(env, context: dict, adapt: AdaptFn, act: ActFn, num_steps: int, seed: int, desc: str | None = None) -> list[dict]:
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


def offline_adaptation(env, context: dict, adapt: AdaptFn, act: ActFn, num_episodes: int, seed: int, desc: str | None = None,
                       video: str | bool | None = None) -> list[dict]:
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
    sem = scipy.stats.sem(values)
    return mean, float(sem * scipy.stats.t.ppf(0.5 + confidence / 2, values.size - 1))
