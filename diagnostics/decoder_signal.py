"""How much would a decoder on u_con learn about the environment, per family and per target?

`--decoder-coef` gives CLAW's context encoder a reward decoder: symlog(r) from a transition (s, a, s') and u_con.
It is an identification signal only where the reward of a transition differs between the family's environments:
a context-free decoder that fits the pooled transitions as well leaves u_con nothing to encode. This script fits
two regressors of each target on pi_con (random-policy) transitions pooled over the environments, one with the
environment's one-hot id (a perfect u_con) and one without, and reports their held-out MSEs:
  reward      symlog(r) from (s, a, s')    the --decoder-coef decoder's target and input
  next state  s' (standardised) from (s, a)    a dynamics target (not in the scripts), for comparison
The gap, 1 - MSE(with id) / MSE(without), is the part of the loss that only identification removes; ~0 means a
decoder on that target cannot identify the environments. Held out: a random fifth of the transitions.

Usage: python diagnostics/decoder_signal.py [--family walker] [--episodes 10] [--steps 3000]
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import torch  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import make_env, num_envs  # noqa: E402
from diagnostics.checks import check_at_least  # noqa: E402


def standardise(train: np.ndarray, test: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    mean, std = train.mean(0), train.std(0)
    std = np.where(std > 1e-6, std, 1.0)  # constant features: only centred
    return torch.as_tensor((train - mean) / std, dtype=torch.float32), torch.as_tensor(
        (test - mean) / std, dtype=torch.float32
    )


def held_out_mse(x_train, y_train, x_test, y_test, steps: int, seed: int = 0, batch: int = 512) -> float:
    """Test MSE (mean over target dimensions) of a claw.hidden_mlp fitted with Adam."""
    torch.manual_seed(seed)
    model = claw.hidden_mlp(x_train.shape[1], 256, y_train.shape[1])
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    for _ in range(steps):
        index = torch.randint(len(x_train), (batch,))
        loss = torch.nn.functional.mse_loss(model(x_train[index]), y_train[index])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        return float(torch.nn.functional.mse_loss(model(x_test), y_test))


def signal(transitions: list[dict], steps: int, test_fraction: float = 0.2, seed: int = 0) -> dict:
    """transitions: one collect_episodes() dict per environment -> {target: (held-out target variance, MSE without id,
    MSE with id, gap)}."""
    pooled = {key: np.concatenate([data[key] for data in transitions]) for key in ("obs", "action", "next_obs", "reward")}
    env_ids = np.eye(len(transitions), dtype=np.float32)[
        np.concatenate([np.full(len(d["reward"]), j) for j, d in enumerate(transitions)])
    ]
    order = np.random.default_rng(seed).permutation(len(env_ids))
    cut = int(len(order) * (1 - test_fraction))
    train, test = order[:cut], order[cut:]
    symlog_reward = claw.symlog(torch.as_tensor(pooled["reward"][:, None])).numpy()
    targets = {
        "reward": (np.c_[pooled["obs"], pooled["action"], pooled["next_obs"]], symlog_reward),
        "next state": (np.c_[pooled["obs"], pooled["action"]], pooled["next_obs"]),
    }
    result = {}
    for name, (inputs, target) in targets.items():
        if name == "next state":  # per-dimension MSE in units of each dimension's spread
            y_train, y_test = standardise(target[train], target[test])
        else:
            y_train, y_test = torch.as_tensor(target[train]), torch.as_tensor(target[test])
        mse = {}
        for with_id in (False, True):
            x = np.c_[inputs, env_ids] if with_id else inputs
            x_train, x_test = standardise(x[train], x[test])
            mse[with_id] = held_out_mse(x_train, y_train, x_test, y_test, steps)
        result[name] = (float(y_test.var(0).mean()), mse[False], mse[True], 1.0 - mse[True] / mse[False])
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--family", default="walker", choices=["walker", "reach", "push", "go1", "cheetah_walker"])
    parser.add_argument("--episodes", type=int, default=10, help="pi_con episodes per environment")
    parser.add_argument("--steps", type=int, default=3000, help="Adam steps per regressor")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    cli = parser.parse_args(argv)
    check_at_least(cli, {"episodes": 1, "steps": 1, "seed": 0, "threads": 1})
    torch.set_num_threads(cli.threads)
    transitions = [
        collect_episodes(make_env(cli.family, j, seed=cli.seed + j), cli.episodes, seed=cli.seed + 1000 + j)
        for j in range(num_envs(cli.family))
    ]
    print(
        f"{cli.family}: {num_envs(cli.family)} environments x {cli.episodes} pi_con episodes "
        f"({sum(len(t['reward']) for t in transitions)} transitions), {cli.steps} Adam steps per regressor"
    )
    print("| target | held-out variance | MSE without the environment's id | with it | gap: 1 - with / without |")
    print("|---|---|---|---|---|")
    result = signal(transitions, cli.steps, seed=cli.seed)
    for name, (variance, without, with_id, gap) in result.items():
        print(f"| {name} | {variance:.4g} | {without:.4g} | {with_id:.4g} | {gap:+.3f} |")
    return result


if __name__ == "__main__":
    main()
