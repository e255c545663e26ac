"""Does a trained Oracle checkpoint use the parameter it is told? Evaluation only, no retraining.

The Oracle (oracle_tdmpc2.py) sees env_param(family, j) appended to environment j's observation. For each test
environment j (--env-ids; default every one) this runs the Oracle's Exp 2 protocol at 0 adaptation steps (its base
weights, --eval-episodes episodes from the reset seeds oracle_tdmpc2.evaluate uses) twice:

  own        j's physics with j's parameter appended: what the Oracle is evaluated on;
  swapped    j's physics with the parameter of environment (j + --swap-offset) mod n appended instead.

Both arms of an environment start from the same torch seed, so they differ only in the parameter. If returns do not
move, the Oracle's planner ignores what it is told; a swapped arm above the own arm means it plans better believing
it is somewhere else. It is the Oracle's counterpart of context_controls.py (CLAW given another environment's context).

    python diagnostics/oracle_controls.py runs/<oracle run>/checkpoint.pt [--swap-offset 10] [--env-ids 0 1 2]
        [--eval-episodes 2] [--compile on] [--out oracle_controls.md] [--json oracle_controls.json]

Nothing finished is lost on interruption: with --json each finished environment is written there (atomically), and
the same command run again takes up the environments that a run on the same weights and settings finished.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import gymnasium  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import oracle_tdmpc2 as oracle  # noqa: E402
from common.envs import env_param, episode_length, make_env, num_envs  # noqa: E402
from common.evaluation import mean_ci, offline_adaptation  # noqa: E402
from diagnostics.checks import check_at_least, read_checkpoint  # noqa: E402


def told_env(family: str, env_id: int, told_id: int, seed: int) -> gymnasium.Env:
    """Environment env_id's physics, its observation followed by environment told_id's parameter (for told_id ==
    env_id exactly what make_env(..., oracle=True) returns)."""
    env, param = make_env(family, env_id, seed=seed), env_param(family, told_id)
    space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(env.observation_space.shape[0] + param.size,), dtype=np.float32)
    return gymnasium.wrappers.TransformObservation(env, lambda obs: np.concatenate([obs, param]).astype(np.float32), space)


def shown(family: str, env_id: int) -> str:
    """An environment's parameter as a person reads it (float32 digits rounded away)."""
    return ", ".join(f"{v:g}" for v in np.round(env_param(family, env_id).astype(float), 4))


def load(path: str):
    """(args, model, discount): the checkpoint's saved arguments and its base weights, in evaluation mode."""
    saved = read_checkpoint(path, "oracle_controls.py", ("oracle_tdmpc2.py",))  # weights suffice: evaluation only
    args = oracle.Args(**{k: v for k, v in saved["args"].items() if k in oracle.Args.__dataclass_fields__})
    args = dataclasses.replace(args, capture_video=False, cuda=False)
    if saved.get("dims"):
        obs_dim, act_dim = saved["dims"]
    else:  # older checkpoints: the dimensions of the Oracle's evaluation environment
        probe = make_env(args.family, 0, oracle=True)
        obs_dim, act_dim = probe.observation_space.shape[0], probe.action_space.shape[0]
    model = oracle.WorldModel(obs_dim, act_dim, args.model_size, args)
    oracle.load_checkpoint(path, model)
    return args, model.eval().requires_grad_(False), oracle.default_discount(args, episode_length(args.family))


def arm_return(loaded, plan, env_id: int, told_id: int, eval_episodes: int) -> float:
    """Mean return of the 0-step offline protocol in environment env_id told environment told_id's parameter."""
    args, model, discount = loaded
    env = told_env(args.family, env_id, told_id, seed=args.seed + 10_000 + env_id)
    weights, state = model.base_weights(), {"mean": None}

    def act(obs, first_step):
        action, state["mean"] = plan(
            model,
            weights,
            torch.as_tensor(obs, dtype=torch.float32),
            None if first_step else state["mean"],
            discount,
            args,
            explore=False,
        )
        return action.numpy()

    torch.manual_seed(args.seed + 40_000 + env_id)  # both arms of env_id draw the same planner noise
    records = offline_adaptation(env, None, lambda context: None, act, eval_episodes, seed=args.seed + 40_000 + env_id)
    return float(np.mean([r["return"] for r in records]))


def controls(
    path: str, swap_offset: int, env_ids, eval_episodes: int, plan=None, json_path: str | None = None, log=print
) -> dict:
    """{"checkpoint", "family", "identity" (weights digest and settings), "envs": {j: {"told": k, "own": return,
    "swapped": return}}}; with json_path
    each finished environment is saved, and a saved run of the same weights and settings is taken up."""
    plan, loaded = plan or oracle.plan, load(path)
    args, model, _ = loaded
    n = num_envs(args.family)
    env_ids = list(range(n)) if env_ids is None else list(env_ids)
    bad = [j for j in env_ids if not 0 <= j < n]
    if bad:
        raise SystemExit(f"error: --env-ids {bad} outside the {n} environments of {args.family}")
    if swap_offset % n == 0:
        raise SystemExit(f"error: --swap-offset {swap_offset} tells every environment its own parameter ({n} environments)")
    identity = {
        "weights": oracle.weights_digest(model),
        "swap_offset": swap_offset,
        "eval_episodes": eval_episodes,
        "compiled": bool(getattr(plan, "is_compiled", False)),
    }
    result = {"checkpoint": path, "family": args.family, "identity": identity, "envs": {}}
    if json_path and os.path.exists(json_path):
        with open(json_path) as f:
            saved = json.load(f)
        if saved.get("identity") == identity:
            result["envs"] = {int(j): v for j, v in saved["envs"].items()}
            log(f"taking up {len(result['envs'])} finished environment(s) from {json_path}")
        else:
            log(f"ignoring {json_path}: saved for other weights or settings")
    for j in env_ids:
        if j in result["envs"]:
            continue
        k = (j + swap_offset) % n
        own, swapped = (arm_return(loaded, plan, j, told, eval_episodes) for told in (j, k))
        result["envs"][j] = {"told": k, "own": own, "swapped": swapped}
        log(
            f"env {j} (parameter {shown(args.family, j)}): own {own:.1f}, told env {k}'s {shown(args.family, k)}: {swapped:.1f}"
        )
        if json_path:  # atomic: an interruption never leaves half a file
            with open(json_path + ".tmp", "w") as f:
                json.dump(result, f, indent=1)
            os.replace(json_path + ".tmp", json_path)
    result["envs"] = {j: result["envs"][j] for j in env_ids}
    return result


def report(result: dict) -> str:
    family, envs, episodes = result["family"], result["envs"], result["identity"]["eval_episodes"]
    lines = [
        f"# Oracle told another environment's parameter: {result['checkpoint']}",
        "",
        f"Exp 2 offline at 0 adaptation steps ({episodes} episode{'s' * (episodes != 1)} per environment "
        f"and arm); swap offset {result['identity']['swap_offset']}; 95% t-CIs over the {len(envs)} environments.",
        "",
        "| env j | its parameter | told env k's | own return | told k's | own - told k's |",
        "|---|---|---|---|---|---|",
    ]
    for j, row in envs.items():
        lines.append(
            f"| {j} | {shown(family, j)} | {shown(family, row['told'])} | "
            f"{row['own']:.1f} | {row['swapped']:.1f} | {row['own'] - row['swapped']:+.1f} |"
        )
    own, swapped = [r["own"] for r in envs.values()], [r["swapped"] for r in envs.values()]
    cells = [mean_ci(v) for v in (own, swapped, np.subtract(own, swapped))]
    lines.append(
        "| mean ± CI | | | "
        + " | ".join(f"{m:.1f} ± {c:.1f}" for m, c in cells[:2])
        + f" | {cells[2][0]:+.1f} ± {cells[2][1]:.1f} |"
    )
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument(
        "--swap-offset", type=int, default=1, help="environment j is told the parameter of environment (j + this) mod n"
    )
    parser.add_argument("--env-ids", type=int, nargs="+", help="only these test environments (default: every one)")
    parser.add_argument("--eval-episodes", type=int, default=2, help="offline episodes per environment and arm")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument(
        "--compile", choices=["on", "off"], default="off", help="on: torch.compile the MPPI planner (long evaluations)"
    )
    parser.add_argument("--out", help="also write the markdown table to this file")
    parser.add_argument("--json", help="also write the result here, environment by environment; a rerun takes it up")
    cli = parser.parse_args(argv)
    check_at_least(cli, {"eval_episodes": 1, "threads": 1, "env_ids": 0})
    torch.set_num_threads(cli.threads)
    plan = oracle.compiled(oracle.plan, torch.device("cpu")) if cli.compile == "on" else oracle.plan
    result = controls(
        cli.checkpoint,
        cli.swap_offset,
        cli.env_ids,
        cli.eval_episodes,
        plan,
        cli.json,
        log=lambda line: print(line, file=sys.stderr, flush=True),
    )
    text = report(result)
    print(text)
    if cli.out:
        with open(cli.out, "w") as f:
            f.write(text + "\n")
    return result


if __name__ == "__main__":
    main()
