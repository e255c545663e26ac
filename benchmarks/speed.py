"""Speed of the hot paths on this machine, eager, compiled (--compile) and as CUDA graphs (--cudagraphs, on the eager or
the compiled functions) side by side, per model size.

Measures, with the real environment and the scripts' own functions (claw_tdmpc2 for CLAW, dr_tdmpc2 for DR):
  loop     agent steps/s of CLAW's pretraining loop body (update + rollout hypernet pass + MPPI + env step)
  update   ms per CLAW two-phase update (world model + hypernet, then policy + hypernet)
  mppi     ms per planner call (adapters already merged)
  compile  s spent in the first calls of the compiled or graphed functions (each input kind the loop and the
           planner meet: first step of an episode or not, exploring or not; compiling, recording the CUDA graphs);
           0 for eager
  adapt    ms per CLAW adaptation: one hypernet pass over 3 pi_con episodes + merge (eager in both modes)
  dr       ms per DR adaptation gradient step on fresh LoRA adapters (base frozen), dr_tdmpc2.adapt_step

Usage: python benchmarks/speed.py [--sizes I F A] [--modes eager compiled cudagraphs compiled-cudagraphs] [--family reach]
       [--steps 30] [--cuda]   (the cudagraphs modes need --cuda)
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
import dr_tdmpc2 as dr  # noqa: E402
from common.context import collect_episodes  # noqa: E402
from common.envs import episode_length, make_env  # noqa: E402


def timed(fn, repeats: int, device: torch.device, warmup: int = 3) -> float:
    """Mean wall-clock milliseconds per call (the GPU synchronised before the clock stops)."""
    for _ in range(warmup):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / repeats * 1000


def first_calls_seconds(calls) -> float:
    """Wall-clock seconds of the first call of each function in `calls` (compile time, for compiled ones)."""
    start = time.perf_counter()
    for call in calls:
        call()
    return time.perf_counter() - start


MODES = {"eager": (False, False), "compiled": (True, False), "cudagraphs": (False, True), "compiled-cudagraphs": (True, True)}


def fast(script, fn, compile: bool, graphs: bool, device: torch.device, planner: bool = False):
    """fn as a script's main() rebinds it for --compile on/off and --cudagraphs (accelerate())."""
    if compile:
        fn = script.compiled(fn, device, cuda_graphs=planner and not graphs)
    return script.graphed(fn) if graphs else fn


def measure(size: str, family: str, steps: int, rank: int, mode: str, device: torch.device) -> dict:
    compile, graphs = MODES[mode]
    torch.manual_seed(0)
    args = claw.Args(family=family, model_size=size, rank=rank)
    env = make_env(family, 0, seed=0)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    discount = claw.default_discount(args, episode_length(family))
    model = claw.WorldModel(obs_dim, act_dim, size, args).to(device)
    layout, n_wm, n_pi = claw.lora_layout(model, rank)
    hypernet = claw.Hypernet(2 * obs_dim + act_dim + 1, claw.lora_template(layout, n_wm + n_pi), args).to(device)
    optimizers = claw.make_optimizers(model, hypernet, args)
    claw.capturable(optimizers, graphs)
    scale = claw.RunningScale(args.tau, device)
    update = fast(claw, claw.update, compile, graphs, device)
    plan = fast(claw, claw.plan, compile, graphs, device, planner=True)

    test_context = collect_episodes(env, args.context_episodes, seed=0)  # 3 pi_con episodes, as at test time
    context = claw.context_tensor(test_context, device)
    replay = claw.ReplayBuffer(len(test_context["obs"]) + 2 * steps + 100, obs_dim, act_dim, 1, args.horizon, device)
    for i in range(len(test_context["obs"])):
        replay.add(
            0,
            test_context["obs"][i],
            test_context["action"][i],
            float(test_context["reward"][i]),
            test_context["next_obs"][i],
            i == 0 or test_context["episode"][i] != test_context["episode"][i - 1],
        )

    def update_step():
        return update(
            model, hypernet, optimizers, scale, layout, n_wm, *replay.sample(0, args.batch_size), context, discount, args
        )

    def adapt():
        with torch.no_grad():
            return claw.adapted_weights(model, hypernet(context), layout)

    weights, obs = adapt(), torch.as_tensor(test_context["obs"][0], device=device)
    state = {"obs": env.reset(seed=0)[0], "first": True, "mean": None}

    def loop_step():  # the body of the pretraining loop
        update_step()
        w = adapt()
        action, state["mean"] = plan(
            model,
            w,
            torch.as_tensor(state["obs"], dtype=torch.float32, device=device),
            None if state["first"] else state["mean"],
            discount,
            args,
            explore=True,
        )
        action = action.cpu().numpy()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        replay.add(0, state["obs"], action, reward, next_obs, state["first"])
        state["obs"], state["first"] = next_obs, False
        if terminated or truncated:
            state["obs"], state["first"] = env.reset()[0], True

    def mppi():
        return plan(model, weights, obs, None, discount, args, False)

    # the first calls: every input kind the loop and the planner measurement meet, compiled here when compile is on
    compile_s = first_calls_seconds([update_step, loop_step, loop_step, mppi])
    result = {
        "size": size,
        "mode": mode,
        "params": sum(p.numel() for p in model.base_parameters()),
        "compile_s": compile_s if compile or graphs else 0.0,
        "update_ms": timed(update_step, steps, device),
        "mppi_ms": timed(mppi, steps, device),
        "adapt_ms": timed(adapt, steps, device),
        "context_rows": len(context),
    }
    result["loop_sps"] = 1000 / timed(loop_step, steps, device)
    result["dr_step_ms"] = dr_gradient_step_ms(size, family, rank, test_context, compile, graphs, device, steps)
    return result


def dr_gradient_step_ms(size, family, rank, test_context, compile, graphs, device, steps) -> float:
    """One test-time gradient step of the gradient-adapted baselines (dr_tdmpc2.adapt_step): the TD-MPC2 loss
    through fresh LoRA adapters on the context data, base frozen, Adam on the adapters only."""
    torch.manual_seed(0)
    args = dr.Args(family=family, model_size=size, rank=rank)
    obs_dim, act_dim = test_context["obs"].shape[1], test_context["action"].shape[1]
    model = dr.WorldModel(obs_dim, act_dim, size, args).to(device).requires_grad_(False)
    layout, n_wm, n_pi = dr.lora_layout(model, rank)
    phi = dr.lora_template(layout, n_wm + n_pi).to(device).requires_grad_(True)
    optimizer = torch.optim.Adam([phi], lr=args.learning_rate, capturable=graphs)
    scale = dr.RunningScale(args.tau, device)
    replay, discount = dr.context_replay(test_context, device, args), dr.default_discount(args, episode_length(family))
    adapt_step = fast(dr, dr.adapt_step, compile, graphs, device)

    def step():
        adapt_step(model, phi, optimizer, scale, layout, *replay.sample(0, args.batch_size), discount, args)

    step()  # compiles when compile is on; timed()'s warm-up records the CUDA graph
    return timed(step, steps, device)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["I", "F"])
    parser.add_argument("--modes", nargs="+", default=["eager", "compiled"], choices=list(MODES))
    parser.add_argument("--family", default="reach")
    parser.add_argument("--rank", type=int, default=16)
    parser.add_argument("--steps", type=int, default=30, help="timed repetitions per measurement")
    parser.add_argument("--cuda", action="store_true", help="measure on the GPU")
    cli = parser.parse_args()
    if not cli.cuda and any(MODES[mode][1] for mode in cli.modes):
        parser.error("the cudagraphs modes need --cuda")
    device = torch.device("cuda" if cli.cuda else "cpu")
    name = torch.cuda.get_device_name() if cli.cuda else f"CPU, {torch.get_num_threads()} threads"
    print(f"torch {torch.__version__}, {name}, family {cli.family}, rank {cli.rank}, {cli.steps} timed repetitions")
    print(
        "| size | mode | base params | loop steps/s | update ms | MPPI ms/action | compile s | CLAW adapt ms (rows) | DR grad step ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for size in cli.sizes:
        for mode in cli.modes:
            r = measure(size, cli.family, cli.steps, cli.rank, mode, device)
            print(
                f"| {size} | {r['mode']} | {r['params']:,} | {r['loop_sps']:.1f} | {r['update_ms']:.1f} | {r['mppi_ms']:.1f} | "
                f"{r['compile_s']:.0f} | {r['adapt_ms']:.2f} ({r['context_rows']}) | {r['dr_step_ms']:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
