"""Does a pi_con context identify the Meta-World goal, and through which statistic?

The Reach/Push goal is hidden from the observation, so an adaptation method can only learn it
from the context's rewards. This script draws several 3-episode random-policy contexts per goal
(as at test time) and classifies the goal four ways:
  mean reward          leave-one-out nearest centroid on the context's mean reward
  + reward~position    the same plus the least-squares slope of reward on the tracked position
  distance form        the candidate goal whose distance to the tracked position best
                       rank-correlates (negatively) with reward: an upper bound that knows the
                       reward falls with that distance
  learned encoder      CLAW's own context encoder (h_emb, mean pool, h_con, from
                       claw_tdmpc2.py) plus a linear head, trained supervised on the goal label
                       from separate contexts: can the architecture extract the goal at all?
The tracked position is the hand for Reach and the object for Push.

Usage: python benchmarks/context_identifiability.py [--family reach] [--draws 6] [--probe-pool 10]
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


def train_encoder_probe(train: list, train_labels, test: list, test_labels, steps: int, seed: int = 0,
                        resample: int | None = None) -> int:
    """Fit claw.ContextEncoder + a linear goal head on `train` contexts (tensors [N, 2*obs+act+1]);
    return how many `test` contexts it classifies correctly. With `resample`, every step feeds a
    fresh random `resample` rows of each training tensor, as pretraining samples its context buffer."""
    torch.manual_seed(seed)
    args = claw.Args()
    encoder = claw.ContextEncoder(train[0].shape[1], args)
    head = torch.nn.Linear(args.context_dim, int(max(train_labels)) + 1)
    optimizer = torch.optim.Adam([*encoder.parameters(), *head.parameters()], lr=args.hypernet_lr)
    labels = torch.as_tensor(train_labels)
    for _ in range(steps):
        batch = [c[torch.randint(len(c), (resample,))] for c in train] if resample else train
        logits = head(torch.stack([encoder(c) for c in batch]))
        loss = torch.nn.functional.cross_entropy(logits, labels)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        predicted = head(torch.stack([encoder(c) for c in test])).argmax(1).numpy()
    return int((predicted == np.asarray(test_labels)).sum())


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--family", choices=sorted(TRACKED_SLICE), default="reach")
    parser.add_argument("--draws", type=int, default=6, help="contexts per goal")
    parser.add_argument("--context-episodes", type=int, default=3)
    parser.add_argument("--probe-draws", type=int, default=8, help="training contexts per goal for the learned probe")
    parser.add_argument("--probe-steps", type=int, default=500)
    parser.add_argument("--probe-pool", type=int, default=0,
                        help="instead of fixed contexts, train on 256-transition resamples of a pool of this many "
                             "pi_con episodes per goal (pretraining's context buffer holds 10)")
    opts = parser.parse_args()

    n = num_envs(opts.family)
    goals = np.array([env_param(opts.family, g) for g in range(n)])
    labels, means, slopes, distance_hits, tensors = [], [], [], 0, []
    probe_train, probe_labels = [], []
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
        if opts.probe_pool:  # one pool per goal, presented probe_draws times per step
            pool = claw.context_tensor(collect_episodes(env, opts.probe_pool, seed=10**6 + 1000 * g), "cpu")
            probe_train += [pool] * opts.probe_draws
            probe_labels += [g] * opts.probe_draws
        for draw in range(0 if opts.probe_pool else opts.probe_draws):  # disjoint seeds: never a test context
            probe_train.append(claw.context_tensor(collect_episodes(env, opts.context_episodes, seed=10**6 + 1000 * g + draw), "cpu"))
            probe_labels.append(g)
        start = context["obs"][0, TRACKED_SLICE[opts.family]]
        print(f"goal {g} {goals[g]}: distance from start {np.linalg.norm(goals[g] - start):.3f}, "
              f"mean reward (last draw) {mean[0]:.3f}, position range {np.ptp(position, 0).round(3)}")
    labels, total = np.array(labels), n * opts.draws
    print(f"contexts: {opts.draws} per goal x {n} goals, {opts.context_episodes} pi_con episodes each; chance {total // n}/{total}")
    print(f"mean reward:          {nearest_centroid_accuracy(np.array(means), labels)}/{total}")
    print(f"+ reward~position:    {nearest_centroid_accuracy(np.c_[np.array(means), np.array(slopes)], labels)}/{total}")
    print(f"distance form (bound): {distance_hits}/{total}")
    hits = train_encoder_probe(probe_train, probe_labels, tensors, labels, opts.probe_steps,
                               resample=256 if opts.probe_pool else None)
    source = f"256-transition resamples of a {opts.probe_pool}-episode pool" if opts.probe_pool else "fixed training contexts"
    print(f"learned encoder:      {hits}/{total} ({opts.probe_draws} {source} per goal and step, {opts.probe_steps} Adam steps)")


if __name__ == "__main__":
    main()
