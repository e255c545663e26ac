"""Speed of CLAW's hot paths on this machine, per model size.

Measures, with the real environment and the script's own functions:
  loop   agent steps/s of the pretraining loop body (update + rollout hypernet pass + MPPI + env step)
  update ms per two-phase update (world model + hypernet, then policy + hypernet)
  mppi   ms per planner call (adapters already merged)
  adapt  ms per CLAW adaptation: one hypernet pass over 3 pi_con episodes + merge into the weights
  dr     ms per DR adaptation gradient step on fresh LoRA adapters (base frozen)

Usage: python benchmarks/speed.py [--sizes F I] [--family reach] [--steps 30]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import torch  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import episode_length, make_env  # noqa: E402


def timed(fn, repeats: int, warmup: int = 3) -> float:
    """Mean wall-clock milliseconds per call."""
    for _ in range(warmup):
        fn()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats * 1000


def measure(size: str, family: str, steps: int, rank: int) -> dict:
    torch.manual_seed(0)
    args = claw.Args(family=family, model_size=size, rank=rank)
    env = make_env(family, 0, seed=0)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    ep_len = episode_length(family)
    discount = claw.default_discount(args, ep_len)
    model = claw.WorldModel(obs_dim, act_dim, size, args)
    layout, n_wm, n_pi = claw.lora_layout(model, rank)
    hypernet = claw.Hypernet(2 * obs_dim + act_dim + 1, claw.lora_template(layout, n_wm + n_pi), args)
    optimizers = claw.make_optimizers(model, hypernet, args)
    scale = claw.RunningScale(args.tau, "cpu")

    test_context = collect_episodes(env, args.context_episodes, seed=0)  # 3 pi_con episodes, as at test time
    contexts = [claw.context_tensor(test_context, "cpu")]
    replay = claw.ReplayBuffer(len(test_context["obs"]) + steps + 10, obs_dim, act_dim, 1, args.horizon, "cpu")
    for i in range(len(test_context["obs"])):
        replay.add(0, test_context["obs"][i], test_context["action"][i], float(test_context["reward"][i]),
                   test_context["next_obs"][i], i == 0 or test_context["episode"][i] != test_context["episode"][i - 1])

    def update():
        claw.update(model, hypernet, optimizers, scale, layout, n_wm, *replay.sample(0, args.batch_size),
                    contexts[0], discount, args)

    def adapt():
        with torch.no_grad():
            return claw.adapted_weights(model, hypernet(contexts[0]), layout)

    weights, obs = adapt(), torch.as_tensor(test_context["obs"][0])
    state = {"obs": env.reset(seed=0)[0], "first": True, "mean": None}

    def loop_step():  # the body of the pretraining loop
        update()
        with torch.no_grad():
            w = claw.adapted_weights(model, hypernet(contexts[0]), layout)
        action, state["mean"] = claw.plan(model, w, torch.as_tensor(state["obs"]), None if state["first"] else state["mean"],
                                          discount, args, explore=True)
        next_obs, reward, terminated, truncated, _ = env.step(action.numpy())
        replay.add(0, state["obs"], action.numpy(), reward, next_obs, state["first"])
        state["obs"], state["first"] = next_obs, False
        if terminated or truncated:
            state["obs"], state["first"] = env.reset()[0], True

    result = {"size": size, "params": sum(p.numel() for p in model.base_parameters()),
              "update_ms": timed(update, steps), "mppi_ms": timed(lambda: claw.plan(model, weights, obs, None, discount, args, False), steps),
              "adapt_ms": timed(adapt, steps), "context_rows": len(contexts[0])}
    result["loop_sps"] = 1000 / timed(loop_step, steps)
    result["dr_step_ms"] = dr_gradient_step_ms(model, layout, n_wm + n_pi, replay, scale, discount, args, steps)
    return result


def dr_gradient_step_ms(model, layout, num_params, replay, scale, discount, args, steps) -> float:
    """One test-time gradient step of the gradient-adapted baselines: TD-MPC2 loss through fresh
    LoRA adapters on the context data, base frozen, Adam on the adapters only."""
    model.requires_grad_(False)
    phi = claw.lora_template(layout, num_params).requires_grad_(True)
    optimizer = torch.optim.Adam([phi], lr=args.learning_rate)

    def step():
        obs, action, reward = replay.sample(0, args.batch_size)
        weights = claw.adapted_weights(model, phi, layout)
        loss, zs, _ = claw.world_model_loss(model, weights, obs, action, reward, discount, args)
        loss = loss + claw.policy_loss(model, weights, zs.detach(), scale, args)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([phi], args.grad_clip_norm)
        optimizer.step()

    ms = timed(step, steps)
    model.requires_grad_(True)
    return ms


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["F", "I"])
    parser.add_argument("--family", default="reach")
    parser.add_argument("--rank", type=int, default=16)
    parser.add_argument("--steps", type=int, default=30, help="timed repetitions per measurement")
    cli = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, family {cli.family}, rank {cli.rank}")
    print("| size | base params | loop steps/s | update ms | MPPI ms/action | CLAW adapt ms (rows) | DR grad step ms | DR step / CLAW pass |")
    print("|---|---|---|---|---|---|---|---|")
    for size in cli.sizes:
        r = measure(size, cli.family, cli.steps, cli.rank)
        print(f"| {size} | {r['params']:,} | {r['loop_sps']:.1f} | {r['update_ms']:.1f} | {r['mppi_ms']:.1f} | "
              f"{r['adapt_ms']:.2f} ({r['context_rows']}) | {r['dr_step_ms']:.1f} | {r['dr_step_ms'] / r['adapt_ms']:.1f}x |", flush=True)


if __name__ == "__main__":
    main()
