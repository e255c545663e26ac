"""dr/st/oracle_tdmpc2.py: plain TD-MPC2 pretraining, gradient-adapted LoRA, both protocols."""

import contextlib
import copy
import dataclasses
import io
import os

import pytest
import torch

import dr_tdmpc2 as dr
import oracle_tdmpc2 as oracle
import st_tdmpc2 as st
from common.context import collect_episodes
from common.envs import env_param, make_env

SCRIPTS = {"dr": dr, "st": st, "oracle": oracle}


def tiny_args(script, tmp_path, **overrides):
    """Size I on reach (100-step episodes; evaluated on goals 0 and 5 of 6), tiny planner and batch, a two-point Exp 2
    sweep."""
    base = dict(
        family="reach",
        model_size="I",
        rank=2,
        total_timesteps=700,
        seed_steps=100,
        burst_updates=5,
        batch_size=16,
        num_samples=16,
        num_elites=4,
        num_pi_trajs=2,
        iterations=1,
        context_episodes=1,
        online_eval_steps=100,
        eval_episodes=1,
        offline_adapt_steps=(0, 2),
        eval_env_ids=(0, 5),
        log_every=20,
        checkpoint_every=10_000,
        cuda=False,
        run_dir=str(tmp_path / "run"),
        evaluate_after_training=False,
    )
    if script is st:  # one environment: a 100-step prefill; either way one planner episode follows it
        base["total_timesteps"] = 200
    base.update(overrides)
    return script.Args(**base)


def run(script, args):
    """main(args) -> its stdout, and how many test-time gradient steps it took."""
    calls, adapt_step = [0], script.adapt_step

    def counting_adapt_step(*a, **k):
        calls[0] += 1
        return adapt_step(*a, **k)

    out = io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out):
        mp.setattr(script, "adapt_step", counting_adapt_step)
        script.main(args)
    return out.getvalue(), calls[0]


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    """Lazily run each script's tiny pretraining + both protocols once per module."""
    cache = {}

    def get(name):
        if name not in cache:
            script = SCRIPTS[name]
            args = tiny_args(script, tmp_path_factory.mktemp(name), evaluate_after_training=True)
            cache[name] = (args, *run(script, args))
        return cache[name]

    return get


def load_model(script, args, obs_dim=39, act_dim=4):
    model = script.WorldModel(obs_dim, act_dim, args.model_size, args)
    scale = script.RunningScale(args.tau, "cpu")
    state = script.load_checkpoint(os.path.join(args.run_dir, "checkpoint.pt"), model, scale=scale)
    return model.eval(), scale, state


def scalars(run_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(run_dir).Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_end_to_end_pretraining_and_both_protocols(name, pretrained):
    args, out, adapt_steps = pretrained(name)
    assert out.count("eval env") == 2
    assert "eval offline (0 steps): return" in out and "eval offline (2 steps): return" in out
    # Exp 1: one gradient step per test-time step (none for the oracle); Exp 2: N steps per sweep point
    online_steps = 0 if name == "oracle" else 2 * args.online_eval_steps
    assert adapt_steps == online_steps + 2 * sum(args.offline_adapt_steps)
    logged = scalars(args.run_dir)
    assert {
        "charts/SPS",
        "charts/episodic_return",
        "losses/wm_loss",
        "losses/pi_loss",
        "losses/grad_norm",
        "eval/online/episodic_return",
        "eval/online/env5/episodic_return",
        "eval/online/env0/success",
    } <= set(logged)
    for tag in (
        "eval/offline/episodic_return",
        "eval/offline/success",
        "eval/offline/env0/episodic_return",
        "eval/offline/env5/success",
    ):
        assert [step for step, _ in logged[tag]] == [0, 2], tag  # TensorBoard step = offline gradient steps
    assert [step for step, _ in logged["eval/online/episodic_return"]] == [100]  # test-time step of episode end


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_every_environment_adapts_from_a_fresh_adam_on_the_same_objects(name, pretrained, tmp_path):
    """The compiled adapt_step guards on phi, its Adam and the Q scale: evaluation reuses one of each (new ones per
    environment recompiled it to dynamo's limit), and resets them so each adaptation starts at Adam step 0."""
    script, (args, _, _) = SCRIPTS[name], pretrained(name)
    seen, adapt_step = [], script.adapt_step

    def recording_adapt_step(model, phi, optimizer, scale, *a, **k):
        adam = optimizer.state.get(phi)
        seen.append((id(phi), id(optimizer), id(scale), int(adam["step"]) if adam else 0))
        return adapt_step(model, phi, optimizer, scale, *a, **k)

    eval_args = dataclasses.replace(
        args,
        eval_only=True,
        checkpoint=os.path.join(args.run_dir, "checkpoint.pt"),
        run_dir=str(tmp_path / "eval"),
        online_eval_steps=0,
        offline_adapt_steps=(3,),
    )
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(io.StringIO()):
        mp.setattr(script, "adapt_step", recording_adapt_step)
        script.main(eval_args)
    assert len({tuple(ids) for *ids, _ in seen}) == 1
    assert [step for *_, step in seen] == [0, 1, 2] * 2


def test_eval_only_restores_q_scale_and_takes_any_rank(pretrained, tmp_path):
    args, _, _ = pretrained("dr")
    checkpoint = os.path.join(args.run_dir, "checkpoint.pt")
    assert float(torch.load(checkpoint, weights_only=False)["scale"]) > 0
    eval_args = dataclasses.replace(
        args,
        eval_only=True,
        checkpoint=checkpoint,
        run_dir=str(tmp_path / "eval"),
        rank=4,
        family="reach",
        online_eval_steps=0,
        offline_adapt_steps=(1,),
    )
    with pytest.raises(SystemExit, match="--family walker conflicts with reach"):  # never silently replaced
        run(dr, dataclasses.replace(eval_args, family="walker"))
    out, adapt_steps = run(dr, dataclasses.replace(eval_args, family="reach"))
    assert "adapter parameters: 1468 (world model) + 224 (policy)" in out  # reach from the checkpoint, rank 4
    assert out.count("eval env") == 2 and "eval offline (1 steps)" in out and adapt_steps == 2


def test_resume_continues_a_killed_run(pretrained, tmp_path):
    args, _, _ = pretrained("dr")
    first = torch.load(os.path.join(args.run_dir, "checkpoint.pt"), weights_only=False)
    os.makedirs(tmp_path / "run")
    killed = copy.deepcopy(first)  # as if a 740-step run had been killed after its checkpoint at 700
    killed["args"].update(total_timesteps=740, evaluate_after_training=False)
    torch.save(killed, tmp_path / "run" / "checkpoint.pt")
    with pytest.raises(SystemExit, match="--total-timesteps 2000 conflicts with 740"):
        run(dr, dr.Args(resume=str(tmp_path / "run" / "checkpoint.pt"), total_timesteps=2000))
    out, _ = run(dr, dr.Args(resume=str(tmp_path / "run" / "checkpoint.pt"), threads=1, log_every=10))  # free flags
    assert "at step 700" in out and "step 710/740" in out and "step 720/740" in out
    resumed = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    assert resumed["global_step"] == 740 and resumed["replay"]["size"] == first["replay"]["size"] + 40
    assert not torch.equal(resumed["model"]["qs.weights.0"], first["model"]["qs.weights.0"])  # it trained on


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_fresh_adapters_leave_base_output_unchanged(name):
    script = SCRIPTS[name]
    torch.manual_seed(0)
    args = script.Args(model_size="F", rank=16)
    model = script.WorldModel(24, 6, "F", args).eval()
    layout, n_wm, n_pi = script.lora_layout(model, args.rank)
    phi = script.lora_template(layout, n_wm + n_pi).requires_grad_(True)
    obs, action = torch.randn(32, 24), torch.rand(32, 6) * 2 - 1
    outputs = []
    for weights in (script.adapted_weights(model, phi, layout), model.base_weights()):
        z = model.encode(obs, weights)
        outputs.append(
            (
                z,
                model.next(z, action, weights),
                model.reward_logits(z, action, weights),
                model.Q(z, action, weights, "all"),
                model.Q(z, action, weights, "all", target=True),
                model.policy(z, weights["policy"]),
            )
        )
    for adapted, base in zip(*outputs):
        torch.testing.assert_close(adapted, base, rtol=0, atol=0)
    assert phi.abs().sum() > 0  # the random factor B is what lets gradient reach A


@pytest.mark.parametrize("name", ["dr", "oracle"])
def test_gradient_steps_on_context_data_lower_the_loss(name, pretrained):
    script = SCRIPTS[name]
    args, _, _ = pretrained(name)
    args = dataclasses.replace(args, rank=16, batch_size=64)
    env = make_env("reach", 3, oracle=script is oracle, seed=7)
    model, scale, _ = load_model(script, args, obs_dim=env.observation_space.shape[0])
    model.requires_grad_(False)
    base_before = [p.clone() for p in model.parameters()]
    layout, n_wm, n_pi = script.lora_layout(model, args.rank)
    phi = script.lora_template(layout, n_wm + n_pi).requires_grad_(True)
    phi_before = phi.detach().clone()
    optimizer = torch.optim.Adam([phi], lr=args.learning_rate)
    replay = script.context_replay(collect_episodes(env, 3, seed=8), "cpu", args)
    torch.manual_seed(0)
    batch = replay.sample(0, 256)  # a fixed batch of (H+1)-step windows from the context data

    def loss():
        torch.manual_seed(1)  # same policy noise in the TD target both times
        with torch.no_grad():
            weights = script.adapted_weights(model, phi, layout)
            wm_loss, zs, _ = script.world_model_loss(model, weights, *batch, 0.95, args)
            return float(wm_loss + script.policy_loss(model, weights, zs, script.RunningScale(args.tau, "cpu"), args))

    before = loss()
    adapt_scale = copy.deepcopy(scale)
    for _ in range(30):
        script.adapt_step(model, phi, optimizer, adapt_scale, layout, *replay.sample(0, args.batch_size), 0.95, args)
    after = loss()
    assert after < before - 1e-3, (before, after)
    # only phi moved, in both its slices; the base and its target critic stayed frozen
    assert not torch.equal(phi[:n_wm], phi_before[:n_wm]) and not torch.equal(phi[n_wm:], phi_before[n_wm:])
    for old, new in zip(base_before, model.parameters()):
        assert torch.equal(old, new)


def test_context_replay_windows_stay_inside_episodes():
    args = dr.Args(horizon=3)
    context = collect_episodes(make_env("reach", 0, seed=0), 2, seed=0)
    replay = dr.context_replay(context, "cpu", args)
    assert replay.size == 200 and replay.num_starts(0) == 2 * (100 - args.horizon + 1)
    obs, action, reward = replay.sample(0, 512)
    assert obs.shape == (4, 512, 39) and action.shape == (3, 512, 4) and reward.shape == (3, 512, 1)


def test_st_replay_holds_one_environment_only(tmp_path):
    built = []

    def oracle_make_env(family, env_id, *, oracle=False, seed=None):  # obs then carry env_param: traceable
        built.append(env_id)
        return make_env(family, env_id, oracle=True, seed=seed)

    args = tiny_args(st, tmp_path, train_env_id=4, total_timesteps=200)
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(io.StringIO()):
        mp.setattr(st, "make_env", oracle_make_env)
        st.main(args)
    assert built == [4]
    replay = torch.load(os.path.join(args.run_dir, "checkpoint.pt"), weights_only=False)["replay"]
    assert replay["size"] == 200 and len(replay["starts"]) == 1
    for key in ("obs", "next_obs"):
        assert torch.equal(replay[key][:, -3:], torch.as_tensor(env_param("reach", 4)).expand(200, 3))
    assert "charts/env4/episodic_return" in scalars(args.run_dir)  # labelled by the real environment id


def test_oracle_observations_carry_the_parameter(pretrained):
    args, _, _ = pretrained("oracle")
    state = torch.load(os.path.join(args.run_dir, "checkpoint.pt"), weights_only=False)
    assert state["model"]["encoder.weights.0"].shape[-1] == 39 + 3  # the model's obs dim = base + param dim
    replay = state["replay"]
    assert len(replay["starts"]) == 6
    for env_id, starts in enumerate(replay["starts"]):
        stored = replay["obs"][starts, -3:]
        assert len(starts) > 0 and torch.equal(stored, torch.as_tensor(env_param("reach", env_id)).expand_as(stored))
    # the oracle never zeroes the goal it appends: every env's stored observations differ in it
    assert len({tuple(replay["obs"][s[0], -3:].tolist()) for s in replay["starts"]}) == 6


@pytest.mark.parametrize(
    "name, base, adapter",
    [
        ("dr", 60667, "9600 (world model) + 1792 (policy)"),  # same numbers as CLAW prints
        ("st", 60667, "9600 (world model) + 1792 (policy)"),
        ("oracle", 60731, "9608 (world model) + 1792 (policy)"),  # obs 24 + 1: one more encoder input column
    ],
)
def test_dry_run_prints_exact_counts(name, base, adapter, tmp_path, capsys):
    SCRIPTS[name].main(
        tiny_args(SCRIPTS[name], tmp_path, family="cheetah_walker", eval_env_ids=(), model_size="F", rank=8, dry_run=True)
    )
    out = capsys.readouterr().out
    assert out == f"base parameters: {base}\nadapter parameters: {adapter}\n"
    assert not os.path.exists(tmp_path / "run")


def test_bad_arguments_give_clear_errors(tmp_path):
    with pytest.raises(SystemExit, match=r"--train-env-id must be in 0\.\.5 for family 'reach', got 6"):
        st.main(tiny_args(st, tmp_path, train_env_id=6))
    with pytest.raises(SystemExit, match=r"--train-env-id must be in 0\.\.1 for family 'go1', got -1"):
        st.main(tiny_args(st, tmp_path, family="go1", train_env_id=-1))
    for script in SCRIPTS.values():
        with pytest.raises(SystemExit, match="unknown family 'hopper'"):
            script.main(tiny_args(script, tmp_path, family="hopper"))
        with pytest.raises(SystemExit, match="--offline-adapt-steps must be non-negative"):
            script.main(tiny_args(script, tmp_path, offline_adapt_steps=(0, -1)))
        with pytest.raises(SystemExit, match="--rank must be a positive integer"):
            script.main(tiny_args(script, tmp_path, rank=0))
    assert not os.path.exists(tmp_path / "run")
