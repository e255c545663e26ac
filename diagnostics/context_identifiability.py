"""Does a pi_con context identify the Meta-World goal, and through which statistic?

The Reach/Push goal is hidden from the observation, so an adaptation method can only learn it
from the context's rewards. This script draws several 3-episode random-policy contexts per goal
(as at test time) and classifies the goal four ways:
  mean reward          leave-one-out nearest centroid on the context's mean reward
  + reward~position    the same plus the least-squares slope of reward on the tracked position
  distance form        the candidate goal whose distance to the tracked position best
                       rank-correlates (negatively) with reward: an upper bound that knows the
                       reward falls with that distance
  learned encoder      CLAW's own context encoder (standardisation, h_emb, mean pool, h_con,
                       from claw_tdmpc2.py) plus a linear head, trained supervised on the goal label
                       with contexts drawn as pretraining draws them (--context-episodes whole
                       episodes from a pool of --probe-pool per goal, refreshed by one episode per
                       goal every --probe-refresh steps, or fixed with 0): can the architecture
                       extract the goal at all, and does a fixed pool let it memorise instead?
                       Reports test hits and the u_con between/within-goal ratio on the test contexts.
The tracked position is the hand for Reach and the object for Push.

Usage: python diagnostics/context_identifiability.py [--family reach] [--draws 6] [--probe-refresh 20]
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
import torch  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import env_param, make_env, num_envs  # noqa: E402
from diagnostics.checks import check_at_least  # noqa: E402
from diagnostics.inspect_adapters import between_within  # noqa: E402

TRACKED_SLICE = {"reach": slice(0, 3), "push": slice(4, 7)}  # hand xyz; object xyz


def context_features(context: dict, family: str) -> tuple[np.ndarray, np.ndarray]:
    """(mean reward, slope of reward on the tracked position) of one context."""
    reward, position = context["reward"], context["next_obs"][:, TRACKED_SLICE[family]]
    design = np.c_[np.ones(len(reward)), position - position.mean(0)]
    slope = np.linalg.lstsq(design, reward, rcond=None)[0][1:]
    return np.array([reward.mean()]), slope


def nearest_centroid_accuracy(features: np.ndarray, labels: np.ndarray) -> int:
    """Leave-one-out nearest-centroid hits on standardised features."""
    features = (features - features.mean(0)) / (features.std(0) + 1e-12)
    hits = 0
    for i in range(len(features)):
        others = np.arange(len(features)) != i
        centroids = np.array([features[others & (labels == g)].mean(0) for g in np.unique(labels)])
        hits += int(np.argmin(((centroids - features[i]) ** 2).sum(1)) == labels[i])
    return hits


def train_encoder_probe(
    draw, labels, test: list, test_labels, steps: int, seed: int = 0, statistics: torch.Tensor | None = None
) -> tuple[int, float]:
    """Fit claw.ContextEncoder + a linear goal head; step t trains on the contexts `draw(t)` returns (tensors
    [N, 2*obs+act+1], one per entry of `labels`). `statistics`: rows that fix the standardisation, as the
    initial context pool does in pretraining. Returns (test contexts classified correctly, u_con ratio
    between/within goals on the test contexts)."""
    torch.manual_seed(seed)
    args = claw.Args()
    encoder = claw.ContextEncoder(test[0].shape[1], args)
    if statistics is not None:
        encoder.set_statistics(statistics)
    head = torch.nn.Linear(args.context_dim, int(max(labels)) + 1)
    optimizer = torch.optim.Adam([*encoder.parameters(), *head.parameters()], lr=args.hypernet_lr)
    targets = torch.as_tensor(labels)
    for step in range(steps):
        loss = torch.nn.functional.cross_entropy(head(torch.stack([encoder(c) for c in draw(step)])), targets)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        embeddings = [encoder(c) for c in test]
        predicted = head(torch.stack(embeddings)).argmax(1).numpy()
    index = {}  # (label, k-th context of that label) -> u_con
    for label, u_con in zip(test_labels, embeddings):
        index[int(label), sum(1 for key in index if key[0] == label)] = u_con
    return int((predicted == np.asarray(test_labels)).sum()), between_within(index)[2]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--family", choices=sorted(TRACKED_SLICE), default="reach")
    parser.add_argument("--draws", type=int, default=6, help="contexts per goal")
    parser.add_argument("--context-episodes", type=int, default=3)
    parser.add_argument("--probe-steps", type=int, default=3000)
    parser.add_argument(
        "--probe-pool", type=int, default=20, help="pi_con episodes per goal the probe draws from (as --context-pool-episodes)"
    )
    parser.add_argument(
        "--probe-refresh",
        type=int,
        default=20,
        help="steps between replacing each goal's oldest pool episode by a fresh one; 0: a fixed pool",
    )
    opts = parser.parse_args(argv)
    # two draws per goal: leave-one-out needs another context of the goal; the probe draws whole episodes from its pool
    check_at_least(opts, {"draws": 2, "context_episodes": 1, "probe_steps": 0, "probe_refresh": 0})
    if opts.probe_pool < opts.context_episodes:
        raise SystemExit(
            f"error: --probe-pool must be >= --context-episodes ({opts.context_episodes}): a probe context draws that "
            f"many episodes from the pool, got {opts.probe_pool}"
        )

    n = num_envs(opts.family)
    goals = np.array([env_param(opts.family, g) for g in range(n)])
    labels, means, slopes, distance_hits, tensors, pools = [], [], [], 0, [], []
    pool_size = opts.probe_pool + (opts.probe_steps // opts.probe_refresh if opts.probe_refresh else 0)
    for g in range(n):
        env = make_env(opts.family, g, seed=0)
        for draw in range(opts.draws):
            context = collect_episodes(env, opts.context_episodes, seed=1000 * g + draw)
            mean, slope = context_features(context, opts.family)
            position = context["next_obs"][:, TRACKED_SLICE[opts.family]]
            scores = [scipy.stats.spearmanr(context["reward"], -np.linalg.norm(position - goal, axis=1))[0] for goal in goals]
            distance_hits += int(np.nanargmax(scores) == g)
            labels.append(g)
            means.append(mean)
            slopes.append(slope)
            tensors.append(claw.context_tensor(context, "cpu"))
        pool = collect_episodes(env, pool_size, seed=10**6 + 1000 * g)  # another seed range: never a test context
        pools.append(torch.split(claw.context_tensor(pool, "cpu"), np.bincount(pool["episode"]).tolist()))
        start = context["obs"][0, TRACKED_SLICE[opts.family]]
        print(
            f"goal {g} {goals[g]}: distance from start {np.linalg.norm(goals[g] - start):.3f}, "
            f"mean reward (last draw) {mean[0]:.3f}, position range {np.ptp(position, 0).round(3)}"
        )
    labels, total = np.array(labels), n * opts.draws
    print(
        f"contexts: {opts.draws} per goal x {n} goals, {opts.context_episodes} pi_con episodes each; chance {total // n}/{total}"
    )
    print(f"mean reward:          {nearest_centroid_accuracy(np.array(means), labels)}/{total}")
    print(f"+ reward~position:    {nearest_centroid_accuracy(np.c_[np.array(means), np.array(slopes)], labels)}/{total}")
    print(f"distance form (bound): {distance_hits}/{total}")

    def draw(step):  # one context per goal: whole episodes from the pool's current window
        start = step // opts.probe_refresh if opts.probe_refresh else 0
        return [
            torch.cat([pool[start + i] for i in torch.randperm(opts.probe_pool)[: opts.context_episodes].tolist()])
            for pool in pools
        ]

    initial = torch.cat([episode for pool in pools for episode in pool[: opts.probe_pool]])
    hits, ratio = train_encoder_probe(draw, list(range(n)), tensors, labels, opts.probe_steps, statistics=initial)
    source = f"refreshed every {opts.probe_refresh} steps" if opts.probe_refresh else "fixed"
    print(
        f"learned encoder:      {hits}/{total}, u_con ratio other/same goal {ratio:.2f} ({opts.probe_pool}-episode pool per goal, "
        f"{source}, {opts.probe_steps} Adam steps)"
    )


if __name__ == "__main__":
    main()
