"""Does a trained CLAW hypernetwork tell the environments apart? (context identifiability)

For each environment of the checkpoint's family, collect pi_con context twice (two seeds) and
compare the hypernetwork's context embeddings u_con and generated adapters phi: the distance
between two contexts of the *same* environment (noise) against the distance between
*different* environments (signal). A ratio near 1 means the adapters do not depend on the task.

    python benchmarks/inspect_adapters.py runs/<run>/checkpoint.pt [--episodes 3]
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import torch  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import episode_length, make_env, num_envs  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument("--episodes", type=int, default=3, help="pi_con episodes per context")
    cli = parser.parse_args(argv)
    state = torch.load(cli.checkpoint, map_location="cpu", weights_only=False)
    args = claw.Args(**{k: v for k, v in state["args"].items() if k in claw.Args.__dataclass_fields__})
    env = make_env(args.family, 0)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    model = claw.WorldModel(obs_dim, act_dim, args.model_size, args)
    layout, n_wm, n_pi = claw.lora_layout(model, args.rank)
    hypernet = claw.Hypernet(2 * obs_dim + act_dim + 1, claw.lora_template(layout, n_wm + n_pi), args)
    hypernet.load_state_dict(state["hypernet"])
    model.load_state_dict(state["model"])
    embeddings, adapters = {}, {}
    with torch.no_grad():
        for env_id in range(num_envs(args.family)):
            env = make_env(args.family, env_id)
            for draw in range(2):
                rows = claw.context_tensor(collect_episodes(env, cli.episodes, seed=1000 * draw + env_id), "cpu")
                embeddings[env_id, draw] = hypernet.encoder(rows)
                adapters[env_id, draw] = hypernet(rows)[:n_wm] - hypernet.template[:n_wm]
    n = num_envs(args.family)
    print(f"{cli.checkpoint}: family {args.family}, size {args.model_size}, rank {args.rank}")
    phi_norms = torch.stack([(adapters[e, 0] + hypernet.template[:n_wm]).norm() for e in range(n)])
    print(f"||template (world model)|| = {hypernet.template[:n_wm].norm():.4f}, "
          f"||phi (world model)|| = {phi_norms.mean():.4f} (template + generated delta, mean over environments)")
    for name, values in (("u_con", embeddings), ("delta phi (world model)", adapters)):
        same = torch.stack([(values[e, 0] - values[e, 1]).norm() for e in range(n)]).mean()
        other = torch.stack([(values[a, 0] - values[b, 0]).norm() for a, b in itertools.combinations(range(n), 2)]).mean()
        size = torch.stack([values[e, 0].norm() for e in range(n)]).mean()
        print(f"{name:24s} mean norm {size:.4f} | same env, other context {same:.2e} | other env {other:.2e} | "
              f"ratio {other / same.clamp_min(1e-12):.2f}")
    # where the world-model loss's gradient goes inside the hypernetwork, on the run's own replay
    replay = claw.ReplayBuffer(state["replay"]["size"], obs_dim, act_dim, n, args.horizon, "cpu")
    replay.load_state_dict(state["replay"])
    torch.manual_seed(0)
    phi = hypernet(claw.sample_context(list(state["contexts"]), 0, args.context_batch_size))
    batch, weights = replay.sample(0, args.batch_size), claw.adapted_weights(model, phi, layout)
    discount = claw.default_discount(args, episode_length(args.family))

    def loss_with(**coefs):  # the world-model loss, reseeded so every call draws the same target heads
        torch.manual_seed(1)
        return claw.world_model_loss(model, weights, *batch, discount, dataclasses.replace(args, **coefs))[0]

    penalty = args.adapter_l2 * phi[:n_wm].pow(2).sum()
    (loss_with() + penalty).backward(retain_graph=True)
    parts = {"context encoder": hypernet.encoder, "generator": hypernet.generator}
    norms = {name: torch.cat([p.grad.flatten() for p in part.parameters()]).norm() for name, part in parts.items()}
    norms.update({"chunk embeddings": hypernet.chunk_embeddings.grad.norm(), "template": hypernet.template.grad.norm()})
    print("gradient norms of one world-model loss: " + ", ".join(f"{k} {v:.2e}" for k, v in norms.items()))
    # which weighted loss term reaches the context encoder: only task-dependent terms can teach it the task
    coefs = ("consistency_coef", "reward_coef", "value_coef")
    terms = {c.split("_")[0]: loss_with(**{other: 0.0 for other in coefs if other != c}) for c in coefs}
    terms["adapter L2"] = penalty
    encoder_params = list(hypernet.encoder.parameters())
    split = {name: torch.cat([g.flatten() for g in torch.autograd.grad(term, encoder_params, retain_graph=True)]).norm()
             for name, term in terms.items()}
    print("context-encoder gradient norm by weighted loss term: " + ", ".join(f"{k} {v:.2e}" for k, v in split.items()))


if __name__ == "__main__":
    main()
