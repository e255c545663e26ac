"""Single-process simulator throughput per family: agent steps/s under uniform random actions.

Usage: python benchmarks/env_throughput.py [--steps 2000] [--families walker go1 ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from common.envs import FAMILIES, make_env  # noqa: E402


def measure(family: str, steps: int, seed: int = 0) -> dict[str, float]:
    t0 = time.perf_counter()
    env = make_env(family, 0, seed=seed)
    env.reset()
    t_make = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps,) + env.action_space.shape).astype(np.float32)
    resets = 0
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:  # resets are part of real rollouts, so they are timed
            env.reset()
            resets += 1
    dt = time.perf_counter() - t0
    return {"make_reset_s": t_make, "steps_per_s": steps / dt, "ms_per_step": 1e3 * dt / steps, "resets": resets}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="agent steps per family")
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    args = parser.parse_args()
    print(f"{'family':<16}{'agent steps/s':>14}{'ms/step':>10}{'resets':>8}{'make+reset s':>14}")
    for family in args.families:
        r = measure(family, args.steps)
        print(f"{family:<16}{r['steps_per_s']:>14.0f}{r['ms_per_step']:>10.3f}{r['resets']:>8d}{r['make_reset_s']:>14.2f}")


if __name__ == "__main__":
    main()
