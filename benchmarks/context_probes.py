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
  decoder  an identification loss (a departure, as in VariBAD/PEARL-style decoders): a reward decoder, an MLP on a
         replay transition (s, a, s'; reward slot zeroed, standardised as the context is) and u_con, predicts
         symlog(r) of the replay batch of the same environment; its MSE, weighted DECODER_COEF, joins the phase-1
         loss, so the encoder gets a direct gradient for what tells the rewards of its environment apart. The
         decoder lives in the hypernetwork (trained by its optimiser, saved in its checkpoint); planning and the
         world model are unchanged. Does a self-supervised signal make the encoder read the goal (the goal probe
         shows the rest of CLAW then uses it)? Needs --compile off (the update is patched per call).

    python benchmarks/context_probes.py PROBE train <claw_tdmpc2.py flags>
    python benchmarks/context_probes.py PROBE inspect <checkpoint> [inspect_adapters.py flags]
    python benchmarks/context_probes.py PROBE controls <checkpoint> [context_controls.py flags]

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

import functools  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from benchmarks import context_controls, inspect_adapters  # noqa: E402
from common.context import collect_episodes  # noqa: E402

HIDDEN_GOAL = slice(36, 39)  # Meta-World's goal slots, zeroed by common.envs for the hidden-goal families
DECODER_COEF = 1.0  # against the world-model loss's reward 0.1 / consistency 20; symlog rewards of Reach are 0-2.4
PROBES = ("unorm", "goal", "decoder")


def normalised_forward(self, transitions, plain_forward=claw.ContextEncoder.forward):
    u_con = plain_forward(self, transitions)
    return F.layer_norm(u_con, u_con.shape[-1:])


def goal_revealing_collect(env, *args, **kwargs) -> dict:
    if not hasattr(env.unwrapped, "goal"):
        raise SystemExit("the goal probe needs a Meta-World family (reach, push): other families have no hidden goal")
    context = collect_episodes(env, *args, **kwargs)
    goal = env.unwrapped.goal  # after a reset: Meta-World sets its target there
    for key in ("obs", "next_obs"):
        context[key][:, HIDDEN_GOAL] = np.asarray(goal, dtype=np.float32)
    return context


def decoder_init(self, transition_dim, template, args, plain_init=claw.Hypernet.__init__):
    plain_init(self, transition_dim, template, args)
    self.reward_decoder = claw.hidden_mlp(transition_dim + args.context_dim, args.embed_hidden, 1)


def remembering_forward(self, transitions, plain_forward=claw.ContextEncoder.forward):
    self.last_u_con = plain_forward(self, transitions)  # the update's phase-1 context embedding, for the decoder
    return self.last_u_con


def decoder_loss(hypernet, obs, action, reward) -> torch.Tensor:
    """MSE of the decoder's symlog(r) for the replay batch's transitions [H, B], given the batch's context."""
    encoder = hypernet.encoder
    rows = torch.cat([obs[:-1], action, torch.zeros_like(reward), obs[1:]], -1)  # the context's (s, a, r, s') layout
    rows = (rows - encoder.feature_mean) / encoder.feature_std
    keep = torch.ones(rows.shape[-1], device=rows.device)
    keep[obs.shape[-1] + action.shape[-1]] = 0.0  # the reward is what the decoder predicts
    u_con = encoder.last_u_con.expand(*rows.shape[:-1], -1)
    return F.mse_loss(hypernet.reward_decoder(torch.cat([rows * keep, u_con], -1)), claw.symlog(reward))


def world_model_loss_with_decoder(hypernet, model, weights, obs, action, reward, discount, args,
                                  plain_loss=claw.world_model_loss):
    loss, zs, info = plain_loss(model, weights, obs, action, reward, discount, args)
    identification = decoder_loss(hypernet, obs, action, reward)
    info["decoder_loss"] = identification.detach()
    return loss + DECODER_COEF * identification, zs, info


def decoding_update(model, hypernet, *rest, plain_update=claw.update):
    with mock.patch.object(claw, "world_model_loss", functools.partial(world_model_loss_with_decoder, hypernet)):
        return plain_update(model, hypernet, *rest)


def patches(probe: str) -> list:
    if probe == "unorm":
        return [mock.patch.object(claw.ContextEncoder, "forward", normalised_forward)]
    if probe == "decoder":
        return [mock.patch.object(claw.Hypernet, "__init__", decoder_init),
                mock.patch.object(claw.ContextEncoder, "forward", remembering_forward),
                mock.patch.object(claw, "update", decoding_update)]
    # every place that collects a context for the hypernetwork: pretraining pool and evaluate(), and the two tools
    return [mock.patch.object(module, "collect_episodes", goal_revealing_collect) for module in (claw, inspect_adapters, context_controls)]


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2 or argv[0] not in PROBES or argv[1] not in ("train", "inspect", "controls"):
        raise SystemExit("usage: context_probes.py {unorm,goal,decoder} {train <claw_tdmpc2.py flags> | inspect <checkpoint> [flags]"
                         " | controls <checkpoint> [flags]}")
    probe, tool, rest = argv[0], argv[1], argv[2:]
    with contextlib.ExitStack() as stack:
        for patch in patches(probe):
            stack.enter_context(patch)
        if tool == "train":
            import tyro

            args = tyro.cli(claw.Args, args=rest)
            if probe == "decoder" and args.compile == "on":
                raise SystemExit("error: the decoder probe patches the update per call: run it with --compile off")
            args.compile = "off" if probe == "decoder" else args.compile
            claw.main(args)
        elif tool == "inspect":
            inspect_adapters.main(rest)
        else:
            context_controls.main(rest)


if __name__ == "__main__":
    main()
