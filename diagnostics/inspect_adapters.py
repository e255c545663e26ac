"""Does a trained CLAW hypernetwork tell the environments apart? (context identifiability)

For each environment of the checkpoint's family, draw several contexts and compare the hypernetwork's
context embeddings u_con and generated adapters phi: the distance between two contexts of the *same*
environment (noise) against the distance between *different* environments (signal). A ratio near 1
means the adapters do not depend on the task. Two sources side by side:
  fresh          new pi_con contexts (--episodes each), as at test time: what adaptation can use;
  training pool  draws from the checkpoint's own pretraining context pool, as pretraining draws them.
A training ratio far above the fresh one means the hypernetwork keys on which episodes the pool
holds (a shortcut that does not exist at test time), not on the environment. It also prints what the
planner sees: the merged LoRA update A B of each adapted layer relative to the layer's base weight, and
how far the environments' merged updates are apart (a near-zero or environment-independent update is
a CLAW that plans with its base weights, whatever phi's norm).

    python diagnostics/inspect_adapters.py runs/<run>/checkpoint.pt [--episodes 3] [--draws 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import torch  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import episode_length, make_env, num_envs  # noqa: E402
from diagnostics.checks import check_at_least, read_checkpoint  # noqa: E402


def between_within(values: dict) -> tuple[float, float, float]:
    """values[(env, draw)] -> vector. Mean distance between two draws of one environment, mean
    distance between two environments (same draw index), and their ratio."""
    envs, draws = sorted({e for e, _ in values}), sorted({d for _, d in values})
    same = torch.stack(
        [(values[e, a] - values[e, b]).norm() for e in envs for a, b in itertools.combinations(draws, 2)]
    ).mean()
    other = torch.stack(
        [(values[a, d] - values[b, d]).norm() for a, b in itertools.combinations(envs, 2) for d in draws]
    ).mean()
    return float(same), float(other), float(other / same.clamp_min(1e-12))


def merged_update_sizes(model, phis: list, layout) -> tuple[list[float], list[float]]:
    """Per adapted layer: ||A B|| / ||W0|| of phis[0]'s merged update, and the largest ||A B (phi) - A B (phis[0])|| / ||W0||
    over the other phis. A B is formed from phi's slices as adapted_weights forms it, not as (W0 + A B) - W0: float32
    round-off of that difference (~1e-7 of W0) would hide the updates measured here."""
    base = model.base_weights()
    sizes, spreads = [], []
    for name, layer, a_shape, b_shape, offset in layout:
        mid = offset + math.prod(a_shape)
        updates = [phi[offset:mid].view(a_shape) @ phi[mid : mid + math.prod(b_shape)].view(b_shape) for phi in phis]
        scale = base[name][layer].norm()
        sizes.append(float(updates[0].norm() / scale))
        spreads.append(max((float((u - updates[0]).norm() / scale) for u in updates[1:]), default=0.0))
    return sizes, spreads


def input_sensitivity(encoder, contexts: list, obs_dim: int, act_dim: int) -> dict:
    """Which parts of a transition (s, a, r, s') the context embedding responds to: the RMS entry of the
    Jacobian of u_con with respect to the *standardised* input features (so feature scales do not
    matter), per group, over the features that vary in the contexts (constant ones carry nothing)."""
    rows = torch.cat(contexts)
    varying = rows.std(0) > 1e-6
    groups = {
        "s": slice(0, obs_dim),
        "a": slice(obs_dim, obs_dim + act_dim),
        "r": slice(obs_dim + act_dim, obs_dim + act_dim + 1),
        "s'": slice(obs_dim + act_dim + 1, None),
    }
    squares = torch.zeros(rows.shape[1])
    for context in contexts:
        standardised = ((context - encoder.feature_mean) / encoder.feature_std).requires_grad_(True)
        # [context_dim, N, features]
        jacobian = torch.autograd.functional.jacobian(lambda x: encoder.context(encoder.embed(x).mean(0)), standardised)
        squares += jacobian.pow(2).sum((0, 1)) * len(context)  # N x: the per-row pooling weight is 1/N
    rms = (squares / (len(contexts) * encoder.context[-1].out_features)).sqrt()
    return {
        name: float(rms[group][varying[group]].pow(2).mean().sqrt()) if varying[group].any() else float("nan")
        for name, group in groups.items()
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument("--episodes", type=int, default=3, help="pi_con episodes per fresh context")
    parser.add_argument("--draws", type=int, default=4, help="contexts per environment and source (>= 2)")
    cli = parser.parse_args(argv)
    check_at_least(cli, {"episodes": 1, "draws": 2})  # two draws: the same-environment distance needs a pair
    # the training pool's draws and the gradient probe read the pool and replay that archived checkpoints drop
    state = read_checkpoint(cli.checkpoint, "inspect_adapters.py", ("claw_tdmpc2.py",), needs=("replay", "contexts"))
    args = claw.Args(**{k: v for k, v in state["args"].items() if k in claw.Args.__dataclass_fields__})
    env = make_env(args.family, 0)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    model = claw.WorldModel(obs_dim, act_dim, args.model_size, args)
    layout, n_wm, n_pi = claw.lora_layout(model, args.rank)
    hypernet = claw.Hypernet(2 * obs_dim + act_dim + 1, claw.lora_template(layout, n_wm + n_pi), args)
    try:  # one line, not a size-mismatch traceback per tensor
        hypernet.load_state_dict(state["hypernet"])
        model.load_state_dict(state["model"])
    except (KeyError, RuntimeError) as error:
        raise SystemExit(f"error: {cli.checkpoint} does not fit its own saved arguments: {claw.mismatch(error)}") from None
    n = num_envs(args.family)
    fresh = {}
    for env_id in range(n):
        env = make_env(args.family, env_id)
        for draw in range(cli.draws):
            fresh[env_id, draw] = claw.context_tensor(collect_episodes(env, cli.episodes, seed=1000 * draw + env_id), "cpu")
    pool = claw.ContextPool([None] * n, args, "cpu")
    pool.episodes = state["contexts"][0]
    torch.manual_seed(0)
    training = {(env_id, draw): pool.sample(env_id) for env_id in range(n) for draw in range(cli.draws)}
    print(
        f"{cli.checkpoint}: family {args.family}, size {args.model_size}, rank {args.rank}; "
        f"{cli.draws} contexts per environment and source"
    )
    with torch.no_grad():
        phis = [hypernet(fresh[e, 0]) for e in range(n)]
        phi_norm = torch.stack([phi[:n_wm].norm() for phi in phis]).mean()
        print(
            f"||template (world model)|| = {hypernet.template[:n_wm].norm():.4f}, "
            f"||phi (world model)|| = {phi_norm:.4f} (template + generated delta, mean over environments)"
        )
        sizes, spreads = merged_update_sizes(model, phis, layout)
        print(
            f"merged update ||A B|| / ||W0|| over the {len(sizes)} adapted layers (environment 0, fresh context): median "
            f"{sorted(sizes)[len(sizes) // 2]:.2e}, max {max(sizes):.2e}; largest ||A B (env e) - A B (env 0)|| / ||W0||: "
            f"median {sorted(spreads)[len(spreads) // 2]:.2e}, max {max(spreads):.2e}"
        )
        for source, contexts in (("fresh", fresh), ("training pool", training)):
            embeddings = {key: hypernet.encoder(rows) for key, rows in contexts.items()}
            adapters = {key: hypernet(rows)[:n_wm] - hypernet.template[:n_wm] for key, rows in contexts.items()}
            for name, values in (("u_con", embeddings), ("delta phi (world model)", adapters)):
                same, other, ratio = between_within(values)
                size = torch.stack([v.norm() for v in values.values()]).mean()
                print(
                    f"{source:13s} {name:24s} mean norm {size:.4f} | same env, other context {same:.2e} | "
                    f"other env {other:.2e} | ratio {ratio:.2f}"
                )
    print(
        "u_con sensitivity per standardised input feature (RMS of d u_con / d x over the fresh contexts' varying "
        "features): "
        + ", ".join(
            f"{k} {v:.2e}" for k, v in input_sensitivity(hypernet.encoder, list(fresh.values()), obs_dim, act_dim).items()
        )
    )
    # where the world-model loss's gradient goes inside the hypernetwork, on the run's own replay
    replay = claw.ReplayBuffer(state["replay"]["size"], obs_dim, act_dim, n, args.horizon, "cpu")
    replay.load_state_dict(state["replay"])
    torch.manual_seed(0)
    u_con = hypernet.encoder(training[0, 0])
    phi = hypernet.generate(u_con)
    batch, weights = replay.sample(0, args.batch_size), claw.adapted_weights(model, phi, layout)
    discount = claw.default_discount(args, episode_length(args.family))

    def loss_with(**coefs):  # the world-model loss, reseeded so every call draws the same target heads
        torch.manual_seed(1)
        return claw.world_model_loss(model, weights, *batch, discount, dataclasses.replace(args, **coefs))[0]

    penalty = args.adapter_l2 * phi[:n_wm].pow(2).sum()
    decoder = args.decoder_coef * hypernet.encoder.decoder_loss(u_con, *batch) if args.decoder_coef > 0 else None
    (loss_with() + penalty + (0.0 if decoder is None else decoder)).backward(retain_graph=True)
    encoder_params = [p for name, p in hypernet.encoder.named_parameters() if not name.startswith("reward_decoder.")]
    parts = {"context encoder": encoder_params, "generator": list(hypernet.generator.parameters())}
    norms = {name: torch.cat([p.grad.flatten() for p in params]).norm() for name, params in parts.items()}
    norms.update({"chunk embeddings": hypernet.chunk_embeddings.grad.norm(), "template": hypernet.template.grad.norm()})
    print("gradient norms of one world-model loss: " + ", ".join(f"{k} {v:.2e}" for k, v in norms.items()))
    # which weighted loss term reaches the context encoder: only task-dependent terms can teach it the task
    coefs = ("consistency_coef", "reward_coef", "value_coef")
    terms = {c.split("_")[0]: loss_with(**{other: 0.0 for other in coefs if other != c}) for c in coefs}
    terms["adapter L2"] = penalty
    if decoder is not None:
        terms["reward decoder (--decoder-coef)"] = decoder
    split = {
        name: torch.cat([g.flatten() for g in torch.autograd.grad(term, encoder_params, retain_graph=True)]).norm()
        for name, term in terms.items()
    }
    print("context-encoder gradient norm by weighted loss term: " + ", ".join(f"{k} {v:.2e}" for k, v in split.items()))


if __name__ == "__main__":
    main()
