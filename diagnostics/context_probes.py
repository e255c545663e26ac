"""CLAW with one change, made in this process only: diagnostics of why CLAW does not identify Reach's goal.

These are not method options (the scripts stay the paper's CLAW); each probe patches `claw_tdmpc2` while the
wrapped tool runs and restores it afterwards.

  unorm  u_con layer-normalised (no affine) after the context encoder. On Reach u_con's norm grows while it
         stays nearly constant across contexts, and the generator's first LayerNorm is scale-invariant: does a
         bounded u_con keep the encoder learning? (The paper does not say whether u_con is normalised.)
  goal   every pi_con context carries the true goal in the observation's hidden-goal slots obs[36:39] (Meta-World
         families only); the world model's own observations keep them zeroed. Identification is then trivial
         for the hypernetwork: one standardised feature, constant within a context, differs between goals. If
         CLAW still plans with goal-independent adapters, what fails is its training signal, not its context.

    python diagnostics/context_probes.py PROBE train <claw_tdmpc2.py flags>
    python diagnostics/context_probes.py PROBE inspect <checkpoint> [inspect_adapters.py flags]
    python diagnostics/context_probes.py PROBE controls <checkpoint> [context_controls.py flags]

Inspect and evaluate a probe's checkpoint through the same probe: a goal-probe hypernetwork fed plain
contexts sees all-zero goal slots it never saw in training.
"""

from __future__ import annotations

import contextlib
import os
import sys
from unittest import mock

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import torch.nn.functional as F  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from diagnostics import context_controls, inspect_adapters  # noqa: E402

HIDDEN_GOAL = slice(36, 39)  # Meta-World's goal slots, zeroed by common.envs for the hidden-goal families


def normalised_forward(self, transitions, plain_forward=claw.ContextEncoder.forward):
    u_con = plain_forward(self, transitions)
    return F.layer_norm(u_con, u_con.shape[-1:])


def goal_revealing_collect(env, *args, **kwargs) -> dict:
    if not hasattr(env.unwrapped, "goal"):
        raise SystemExit("error: the goal probe needs a Meta-World family (reach, push): other families have no hidden goal")
    context = collect_episodes(env, *args, **kwargs)
    goal = env.unwrapped.goal  # after a reset: Meta-World sets its target there
    for key in ("obs", "next_obs"):
        context[key][:, HIDDEN_GOAL] = np.asarray(goal, dtype=np.float32)
    return context


def patches(probe: str) -> list:
    if probe == "unorm":
        return [mock.patch.object(claw.ContextEncoder, "forward", normalised_forward)]
    # every place that collects a context for the hypernetwork: pretraining pool and evaluate(), and the two tools
    return [
        mock.patch.object(module, "collect_episodes", goal_revealing_collect)
        for module in (claw, inspect_adapters, context_controls)
    ]


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2 or argv[0] not in ("unorm", "goal") or argv[1] not in ("train", "inspect", "controls"):
        raise SystemExit(
            f"error: context_probes.py takes a probe (unorm, goal) and a tool (train, inspect, controls), got "
            f"{' '.join(argv[:2]) or 'nothing'}; e.g. context_probes.py goal inspect <checkpoint> [inspect_adapters.py flags]"
        )
    probe, tool, rest = argv[0], argv[1], argv[2:]
    with contextlib.ExitStack() as stack:
        for patch in patches(probe):
            stack.enter_context(patch)
        if tool == "train":
            import tyro

            claw.main(tyro.cli(claw.Args, args=rest))
        elif tool == "inspect":
            inspect_adapters.main(rest)
        else:
            context_controls.main(rest)


if __name__ == "__main__":
    main()
