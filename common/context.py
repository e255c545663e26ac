"""Context-data collection: whole episodes from one environment (the paper's pi_con)."""

from __future__ import annotations

from typing import Callable

import gymnasium
import numpy as np


def collect_episodes(
    env: gymnasium.Env, num_episodes: int, policy: Callable[[np.ndarray], np.ndarray] | None = None, seed: int | None = None
) -> dict[str, np.ndarray]:
    """Roll ``policy`` for ``num_episodes`` whole episodes (until terminated or truncated).

    Default policy: actions uniform in ``env.action_space`` from a generator seeded by ``seed``.
    The first reset uses ``seed``, later resets continue the env's RNG, so the result is
    deterministic given ``seed``. Returns flat float32 arrays ``obs``, ``action``, ``reward``,
    ``next_obs``, ``success`` and int64 ``episode`` (0..num_episodes-1) marking boundaries.
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    if policy is None:
        # Own generator rather than env.action_space.seed(): leaves the env's space RNG untouched.
        rng = np.random.default_rng(seed)
        low, high = env.action_space.low, env.action_space.high
        policy = lambda _obs: rng.uniform(low, high).astype(np.float32)  # noqa: E731

    obs_l, act_l, rew_l, next_l, ep_l, succ_l = [], [], [], [], [], []
    for ep in range(num_episodes):
        obs, _ = env.reset(seed=seed if ep == 0 else None)
        done = False
        while not done:
            action = np.asarray(policy(obs), dtype=np.float32)
            next_obs, reward, terminated, truncated, info = env.step(action)
            obs_l.append(obs)
            act_l.append(action)
            rew_l.append(reward)
            next_l.append(next_obs)
            ep_l.append(ep)
            succ_l.append(info.get("success", 0.0))
            obs, done = next_obs, terminated or truncated

    return {
        "obs": np.asarray(obs_l, dtype=np.float32),
        "action": np.asarray(act_l, dtype=np.float32),
        "reward": np.asarray(rew_l, dtype=np.float32),
        "next_obs": np.asarray(next_l, dtype=np.float32),
        "episode": np.asarray(ep_l, dtype=np.int64),
        "success": np.asarray(succ_l, dtype=np.float32),
    }
