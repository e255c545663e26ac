"""How much does the context change what the world model predicts? CLAW, FiLM, Concat and post-hoc checkpoints.

For each environment j of the checkpoint's family, on a batch of j's own replay transitions (s, a), the world model's
predictions (latent z, next latent, reward, Q averaged over the ensemble, the policy prior's action under one fixed
noise draw) are computed with the conditioning generated from a fresh pi_con context of j ("own"), and compared with:

  same   a second fresh context of j           the noise of drawing a context
  swap   a fresh context of (j + 1) mod n      what the context's environment changes
  base   no conditioning (phi = 0: the base weights; CLAW, FiLM and post-hoc only)

as the relative change ||f(other) - f(own)|| / ||f(own)|| over the batch, averaged over --draws context pairs. A swap
change no larger than the same-environment one means predictions do not depend on whose context the model sees: the
method plans as one context-free model would, whatever its adapters' size (base) says. Unlike
`context_controls.py` (returns, minutes to hours) this reads the model directly and takes seconds; unlike
`inspect_adapters.py` (CLAW's u_con and LoRA factors) it measures every in-context method on the same scale.
Computed in float64, so changes down to ~1e-12 are resolved.

    python diagnostics/context_effect.py runs/<run>/checkpoint.pt [--episodes 3] [--draws 3] [--batch 256] [--out effect.md]

The sweep launcher (`sweep.py`) runs it on every CLAW, FiLM, Concat and post-hoc run it finishes and keeps
context_effect.md in the run's archive, which outlives the checkpoint.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import torch  # noqa: E402

from common.context import collect_episodes  # noqa: E402
from common.envs import make_env, num_envs  # noqa: E402
from diagnostics.checks import check_at_least, read_checkpoint  # noqa: E402

METHODS = ("claw_tdmpc2.py", "film_tdmpc2.py", "concat_tdmpc2.py", "posthoc_tdmpc2.py")
OUTPUTS = ("latent", "next latent", "reward", "Q", "policy action")
ARMS = ("same", "swap", "base")


@contextlib.contextmanager
def float64():
    """Build and run in float64: relative changes of 1e-7 and below are float32 round-off otherwise."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def build(method, state: dict):
    """The checkpoint's world model and a function context rows -> the weights its planner uses (None: no conditioning)."""
    args = method.Args(**{k: v for k, v in state["args"].items() if k in method.Args.__dataclass_fields__})
    obs_dim, act_dim = state["dims"]
    model = method.WorldModel(obs_dim, act_dim, args.model_size, args)
    model.load_state_dict(state["model"])
    transition_dim = 2 * obs_dim + act_dim + 1
    if hasattr(method, "conditioned_weights"):  # Concat: u_con joins the encoder input
        encoder = method.ContextEncoder(transition_dim, args)
        encoder.load_state_dict(state["hypernet"])
        return args, model, lambda rows: method.conditioned_weights(model, encoder(rows)) if rows is not None else None
    if hasattr(method, "film_layout"):
        layout, n_wm, n_pi = method.film_layout(model)
        template = torch.zeros(n_wm + n_pi)
    else:  # CLAW and post-hoc: LoRA
        layout, n_wm, n_pi = method.lora_layout(model, args.rank)
        template = method.lora_template(layout, n_wm + n_pi)
    hypernet = method.Hypernet(transition_dim, template, args)
    hypernet.load_state_dict(state["hypernet"])
    return (
        args,
        model,
        lambda rows: method.adapted_weights(model, hypernet(rows) if rows is not None else torch.zeros(n_wm + n_pi), layout),
    )


def predictions(method, model, weights, obs, action, args) -> dict:
    z = model.encode(obs, weights)
    torch.manual_seed(0)  # one noise draw for the policy prior, the same in every arm
    return {
        "latent": z,
        "next latent": model.next(z, action, weights),
        "reward": method.two_hot_inv(model.reward_logits(z, action, weights), args),
        "Q": method.two_hot_inv(model.Q(z, action, weights, "all"), args).mean(0),
        "policy action": model.pi(z, weights)[0],
    }


@torch.no_grad()
def context_effect(method, model, weights_for, args, batches: dict, contexts: dict) -> dict:
    """batches[j] = (obs [B, obs_dim], action [B, act_dim]); contexts[(j, draw)] = rows. -> {env: {arm: {output: mean
    relative change}}}; the base arm is absent for a method without unconditioned weights (Concat)."""
    envs, draws = sorted({e for e, _ in contexts}), sorted({d for _, d in contexts})
    weights = {key: weights_for(rows) for key, rows in contexts.items()}  # one conditioning per context, reused by every arm
    base = weights_for(None)
    results = {}
    for j in sorted(batches):
        other = envs[(envs.index(j) + 1) % len(envs)]
        arms = {arm: {name: [] for name in OUTPUTS} for arm in ARMS if arm != "base" or base is not None}
        for d in draws:
            own = predictions(method, model, weights[j, d], *batches[j], args)
            versus = {"same": weights[j, draws[(draws.index(d) + 1) % len(draws)]], "swap": weights[other, d], "base": base}
            for arm, values in arms.items():
                for name, f in predictions(method, model, versus[arm], *batches[j], args).items():
                    values[name].append(float((f - own[name]).norm() / own[name].norm().clamp_min(1e-30)))
        results[j] = {arm: {name: sum(v) / len(v) for name, v in values.items()} for arm, values in arms.items()}
    return results


def markdown(results: dict) -> str:
    """Per output: each arm's relative change, mean over environments / largest environment, and swap / same (ratio
    of the means: about 1, the predictions do not depend on whose context the model sees)."""
    arms = [arm for arm in ARMS if all(arm in r for r in results.values())]
    mean = lambda arm, name: sum(r[arm][name] for r in results.values()) / len(results)  # noqa: E731
    lines = [
        "| relative change of | " + " | ".join(f"{arm} (mean / max env)" for arm in arms) + " | swap / same |",
        "|---|" + "---|" * (len(arms) + 1),
    ]
    for name in OUTPUTS:
        cells = [f"{mean(arm, name):.2e} / {max(r[arm][name] for r in results.values()):.2e}" for arm in arms]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {mean('swap', name) / max(mean('same', name), 1e-300):.1f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument("--episodes", type=int, default=3, help="pi_con episodes per fresh context")
    parser.add_argument("--draws", type=int, default=3, help="fresh contexts per environment (>= 2)")
    parser.add_argument("--batch", type=int, default=256, help="replay transitions per environment")
    parser.add_argument("--out", help="also write the report (markdown) here")
    cli = parser.parse_args(argv)
    check_at_least(cli, {"draws": 2, "episodes": 1, "batch": 1})
    # the batches are the run's own replay transitions, which archived checkpoints drop
    state = read_checkpoint(cli.checkpoint, "context_effect.py", METHODS, needs=("replay",))
    method = importlib.import_module(state["method"].removesuffix(".py"))
    family, n = state["args"]["family"], num_envs(state["args"]["family"])
    with float64():
        args, model, weights_for = build(method, state)
        model.eval()
        replay = method.ReplayBuffer(state["replay"]["size"], *state["dims"], n, args.horizon, "cpu")
        replay.load_state_dict(state["replay"])
        torch.manual_seed(0)
        batches, contexts = {}, {}
        for j in range(n):
            if replay.num_starts(j):  # post-hoc's pass 1 fills only walker's buffer; its cheetah still gives swap contexts
                obs, action, _ = replay.sample(j, cli.batch)
                batches[j] = (obs[0].double(), action[0].double())
            env = make_env(family, j)
            for d in range(cli.draws):  # seeds apart from the evaluation's and the pretraining pool's
                contexts[j, d] = method.context_tensor(
                    collect_episodes(env, cli.episodes, seed=3_000_000_000 + 1000 * d + j), "cpu"
                ).double()
        results = context_effect(method, model, weights_for, args, batches, contexts)
    missing = sorted(set(range(n)) - set(batches))
    report = (
        f"{cli.checkpoint}: {state['method']}, family {family}, size {args.model_size}; {len(batches)} environments "
        f"with replay ({cli.batch} transitions each), {cli.draws} fresh {cli.episodes}-episode contexts each"
        + (f"; no replay for environment(s) {missing}" if missing else "")
        + "\n\n"
        + markdown(results)
        + "\n"
    )
    print(report, end="")
    if cli.out:
        with open(cli.out, "w") as f:
            f.write(report)
    return results


if __name__ == "__main__":
    main()
