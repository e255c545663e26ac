"""Does a trained CLAW checkpoint use its context? Evaluation-only controls, no retraining.

  own vs swapped   for every test environment j of the family, CLAW's own evaluation (claw_tdmpc2.evaluate:
                   one hypernet pass on a fresh pi_con context, adapters frozen, --eval-episodes episodes) with
                   (a) j's own context and (b) the context of environment (j + --swap-offset) mod n, every other
                   seed and random number the same (paired). If returns do not drop with the swapped context,
                   the adapters do not depend on the task. With --online-eval-steps > 0 the Exp 1 online
                   protocol runs too, before the offline one in each environment, as evaluate() runs them.
  context size     the own-context offline protocol with contexts of 1, 3, 10 pi_con episodes (--context-episodes).

Each arm is one call of claw_tdmpc2.evaluate with the checkpoint's saved arguments (seed, planner, context
episodes, the test environments of --eval-env-ids; --eval-episodes and --online-eval-steps from here), started from
the torch random state that `claw_tdmpc2.py --eval-only` starts from: the own arm reports exactly what
    python claw_tdmpc2.py --eval-only --checkpoint CKPT --seed S --eval-episodes N --online-eval-steps M \\
        --context-episodes K  (and the checkpoint's planner flags: --num-samples, --iterations, ...)
reports. The swapped arm feeds the hypernetwork the other environment's context (collected with that
environment's evaluation seeds) wherever evaluate() feeds it environment j's own. With --compile on the planner
is torch.compile'd: its random streams differ from eager's, so the own arm is then CLAW's evaluation protocol but no
longer matches `claw_tdmpc2.py --eval-only` bit for bit.

    python diagnostics/context_controls.py runs/<run>/checkpoint.pt [--swap-offset 1] [--context-episodes 1 3 10]
        [--eval-episodes 10] [--online-eval-steps 0] [--compile off] [--out controls.md] [--json controls.json]
        [--progress PREFIX]

Nothing finished is lost on interruption: with --progress (default: the --json path) each finished arm, and inside
an arm each finished environment (claw_tdmpc2.evaluate's own progress file), is saved under PREFIX.*; the same
command run again takes them up (for the same checkpoint weights and settings) and gives the numbers an
uninterrupted run gives. They are removed once the result is written.

--json writes the dict that controls() returns; JSON turns its integer keys (environments, context sizes) into strings,
and an online arm that finishes no episode is NaN there, as Python's json writes and reads it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import glob
import hashlib
import io
import json
import os
import random
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import numpy as np  # noqa: E402
import torch  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import episode_length, make_env, num_envs  # noqa: E402
from common.evaluation import mean_ci  # noqa: E402
from diagnostics.checks import check_at_least, read_checkpoint  # noqa: E402


class NullWriter:
    """What evaluate() logs to: nothing (this tool prints its own tables)."""

    log_dir = os.devnull

    def add_scalar(self, *args, **kwargs):
        pass

    def flush(self):
        pass


def own_context(args: claw.Args, env_id: int, episodes: int) -> torch.Tensor:
    """Environment env_id's evaluation context as evaluate() collects it (same environment and context seeds)."""
    env = make_env(args.family, env_id, seed=args.seed + 10_000 + env_id)
    return claw.context_tensor(collect_episodes(env, episodes, seed=args.seed + 20_000 + env_id), "cpu")


class SwappedContext(torch.nn.Module):
    """The hypernetwork, fed environment (j + offset) mod n's context wherever it is given environment j's own."""

    def __init__(self, hypernet: torch.nn.Module, contexts: list, offset: int):
        super().__init__()
        self.hypernet, self.contexts, self.offset = hypernet, contexts, offset

    def forward(self, transitions):
        matches = [
            j for j, rows in enumerate(self.contexts) if rows.shape == transitions.shape and torch.equal(rows, transitions)
        ]
        if len(matches) != 1:
            raise RuntimeError(f"the hypernet input matches {len(matches)} environments' own contexts, expected exactly one")
        return self.hypernet(self.contexts[(matches[0] + self.offset) % len(self.contexts)])


def load(path: str):
    """(args, model, hypernet, layout, discount, rng): the checkpoint's saved arguments, its networks, and the torch
    random state that `claw_tdmpc2.py --eval-only` has when it calls evaluate()."""
    saved = read_checkpoint(path, "context_controls.py", ("claw_tdmpc2.py",))  # weights suffice: evaluation only
    args = claw.Args(**{k: v for k, v in saved["args"].items() if k in claw.Args.__dataclass_fields__})
    args = dataclasses.replace(args, capture_video=False, compile="off", cuda=False)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    obs_dim, act_dim = saved.get("dims") or (
        make_env(args.family, 0).observation_space.shape[0],
        make_env(args.family, 0).action_space.shape[0],
    )
    model = claw.WorldModel(obs_dim, act_dim, args.model_size, args)  # as claw.main builds them: same random draws
    layout, n_wm, n_pi = claw.lora_layout(model, args.rank)
    hypernet = claw.Hypernet(2 * obs_dim + act_dim + 1, claw.lora_template(layout, n_wm + n_pi), args)
    rng = torch.get_rng_state()
    claw.load_checkpoint(path, model, hypernet)
    return args, model, hypernet, layout, claw.default_discount(args, episode_length(args.family)), rng


def run_arm(loaded, hypernet_input, eval_args: claw.Args, progress_path: str | None = None) -> dict:
    """One claw_tdmpc2.evaluate() call from the --eval-only random state -> {"offline": {env: mean return},
    "online": {env: mean return over the finished online episodes (NaN: none finished)}} (no "online" without online steps).
    progress_path: evaluate()'s per-environment progress file, taken up if an interrupted arm left one."""
    args, model, hypernet, layout, discount, rng = loaded
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.set_rng_state(rng)
    with contextlib.redirect_stdout(io.StringIO()):  # evaluate's own per-environment lines
        results = claw.evaluate(
            model, hypernet_input, layout, discount, NullWriter(), torch.device("cpu"), eval_args, progress_path
        )
    return {
        protocol: {
            env_id: float(np.mean([r["return"] for r in records])) if records else float("nan")
            for env_id, records in results[protocol].items()
        }
        for protocol in ("offline", "online")
        if protocol == "offline" or eval_args.online_eval_steps > 0
    }


def load_finished_arms(progress: str | None, identity: tuple, log) -> dict:
    """The arms an interrupted run of the same checkpoint weights and settings finished ({} if none)."""
    if not progress or not os.path.exists(progress + ".arms.pt"):
        return {}
    saved = torch.load(progress + ".arms.pt", weights_only=False)
    if saved["identity"] != identity:
        log(f"ignoring {progress}.arms.pt: saved for other checkpoint weights or settings")
        return {}
    log(f"resumed from {progress}.arms.pt: {len(saved['arms'])} arms done")
    return saved["arms"]


def controls(
    path: str,
    swap_offset: int = 1,
    context_episodes=(1, 3, 10),
    eval_episodes: int = 10,
    online_eval_steps: int = 0,
    log=print,
    progress: str | None = None,
) -> dict:
    """{"context_episodes": K (the checkpoint's), "swap": {"own"|"swapped": {"offline"|"online": {env: return}}},
    "size": {k: {env: offline return}}}. progress: prefix of the files that let an interrupted run go on."""
    loaded = load(path)
    args, model, hypernet = loaded[0], loaded[1], loaded[2]
    n = num_envs(args.family)
    if swap_offset % n == 0:
        raise SystemExit(
            f"error: --swap-offset {swap_offset} is a multiple of the {n} environments of {args.family}: "
            "every environment would get its own context"
        )
    # what the saved arms' numbers depend on besides their keys; a compiled planner draws other random streams
    identity = (
        claw.weights_digest(model),
        claw.weights_digest(hypernet),
        eval_episodes,
        getattr(claw.plan, "is_compiled", False),
    )
    cache = load_finished_arms(progress, identity, log)
    # evaluate() checks its progress file against the model weights only: the per-arm files carry the whole identity
    # in their names, so one left by other settings is never taken up (and is removed here)
    tag = hashlib.sha256(repr(identity).encode()).hexdigest()[:12]
    for saved in glob.glob(glob.escape(progress) + ".arm-*.pt") if progress else []:
        if not saved.startswith(f"{progress}.arm-{tag}-"):
            log(f"removing {saved}: saved for other checkpoint weights or settings")
            os.remove(saved)

    def arm(episodes: int, offset: int | None, online_steps: int) -> dict:
        key = (episodes, offset, online_steps)  # every arm is deterministic: equal keys give equal numbers
        if key not in cache:
            log(
                f"arm: {episodes}-episode contexts, {'own' if offset is None else f'swapped by {offset}'}, "
                f"{online_steps} online steps, {eval_episodes} offline episodes per environment"
            )
            eval_args = dataclasses.replace(
                args, context_episodes=episodes, eval_episodes=eval_episodes, online_eval_steps=online_steps
            )
            hypernet_input = (
                hypernet
                if offset is None
                else SwappedContext(hypernet, [own_context(args, j, episodes) for j in range(n)], offset)
            )
            cache[key] = run_arm(
                loaded, hypernet_input, eval_args, progress and f"{progress}.arm-{tag}-{episodes}-{offset}-{online_steps}.pt"
            )
            if progress:  # atomic, as evaluate()'s own progress file
                torch.save({"identity": identity, "arms": cache}, progress + ".arms.tmp")
                os.replace(progress + ".arms.tmp", progress + ".arms.pt")
        return cache[key]

    k = args.context_episodes
    return {
        "family": args.family,
        "n_envs": n,
        "context_episodes": k,
        "swap_offset": swap_offset,
        "eval_episodes": eval_episodes,
        "online_eval_steps": online_eval_steps,
        "swap": {"own": arm(k, None, online_eval_steps), "swapped": arm(k, swap_offset, online_eval_steps)},
        "size": {e: arm(e, None, 0)["offline"] for e in context_episodes},
    }


def table(header: list[str], columns: list[dict]) -> list[str]:
    """Markdown rows: one per evaluated environment, then their mean with its 95% t-CI across environments."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for env_id in columns[0]:
        lines.append(f"| {env_id} | " + " | ".join(f"{c[env_id]:.1f}" for c in columns) + " |")
    cells = []
    for c in columns:
        mean, ci = mean_ci([c[e] for e in columns[0]])
        cells.append(f"{mean:.1f} ± {ci:.1f}")
    lines.append("| mean ± 95% CI | " + " | ".join(cells) + " |")
    return lines


def report(path: str, result: dict) -> str:
    n, k, o = result["n_envs"], result["context_episodes"], result["swap_offset"]
    evaluated = len(result["swap"]["own"]["offline"])  # the checkpoint's --eval-env-ids, or all n
    lines = [
        f"# Context controls: {path}",
        "",
        f"family {result['family']}, {evaluated} of its {n} environments; returns are means over {result['eval_episodes']} offline episodes "
        "per environment; the mean row is the mean over environments with its 95% t-CI across environments.",
        "",
    ]
    protocols = [("offline", "Exp 2 offline protocol (one hypernet pass, adapters frozen)")]
    if result["online_eval_steps"] > 0:
        protocols.append(
            ("online", f"Exp 1 online protocol ({result['online_eval_steps']} steps; mean return of the finished episodes)")
        )
    for protocol, title in protocols:
        own, swapped = result["swap"]["own"][protocol], result["swap"]["swapped"][protocol]
        drop = {e: own[e] - swapped[e] for e in own}
        lines += [
            f"## Own vs swapped context: {title}, {k}-episode contexts",
            "",
            *table(["env j", "own context", f"context of env (j+{o}) mod {n}", "own - swapped"], [own, swapped, drop]),
            "",
        ]
    sizes = result["size"]
    lines += [
        "## Context size: own-context offline protocol",
        "",
        *table(["env j", *[f"{e} episode{'s' * (e != 1)}" for e in sizes]], list(sizes.values())),
        "",
    ]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument(
        "--swap-offset", type=int, default=1, help="environment j gets the context of environment (j + this) mod n"
    )
    parser.add_argument(
        "--context-episodes", type=int, nargs="+", default=[1, 3, 10], help="pi_con episodes per context (size control)"
    )
    parser.add_argument("--eval-episodes", type=int, default=10, help="Exp 2 offline episodes per environment and arm")
    parser.add_argument(
        "--online-eval-steps", type=int, default=0, help="Exp 1 online steps per environment and swap arm (0: none)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument(
        "--compile",
        choices=["on", "off"],
        default="off",
        help="on: torch.compile the MPPI planner for long evaluations (~1.7x faster on a CPU at size F, "
        "after ~1 minute of compiling once); the hypernet pass runs once per context and stays eager. "
        "Compiled and eager draw other random streams: the own arm then differs from --eval-only's numbers",
    )
    parser.add_argument("--out", help="also write the markdown tables to this file")
    parser.add_argument("--json", help="also write the result as JSON to this file (atomically)")
    parser.add_argument("--progress", help="prefix of the files that let an interrupted run go on (default: the --json path)")
    cli = parser.parse_args(argv)
    check_at_least(cli, {"context_episodes": 1, "eval_episodes": 1, "online_eval_steps": 0, "threads": 1})
    torch.set_num_threads(cli.threads)
    if cli.compile == "on":  # evaluate() looks plan up in claw's globals, as claw.main's own --compile rebinding relies on
        claw.plan = claw.compiled(claw.plan, torch.device("cpu"))
    progress = cli.progress or cli.json
    result = controls(
        cli.checkpoint,
        cli.swap_offset,
        cli.context_episodes,
        cli.eval_episodes,
        cli.online_eval_steps,
        log=lambda line: print(line, file=sys.stderr, flush=True),
        progress=progress,
    )
    text = report(cli.checkpoint, result)
    print(text)
    if cli.out:
        with open(cli.out, "w") as f:
            f.write(text + "\n")
    if cli.json:  # a sweep reads it: never a half-written file
        with open(cli.json + ".tmp", "w") as f:
            json.dump(result, f, indent=1)
        os.replace(cli.json + ".tmp", cli.json)
    if progress and os.path.exists(progress + ".arms.pt"):  # the result is written: nothing left to resume
        os.remove(progress + ".arms.pt")
    return result


if __name__ == "__main__":
    main()
