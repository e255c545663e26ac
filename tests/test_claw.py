"""claw_tdmpc2.py: exact architecture, LoRA/hypernet mechanics, planner, determinism, resume, e2e."""

import dataclasses
import os

import pytest
import torch

import claw_tdmpc2 as claw
from common.envs import episode_length, make_env

# Paper Table "Experiment 3 model-size sweep" (24-dim observation, 6-dim action).
PAPER_PARAMS = {"A": 4_960_618, "B": 1_214_651, "D": 325_467, "E": 161_787, "F": 60_667, "G": 25_467, "H": 11_707, "I": 5_787}


def tiny_args(tmp_path, **overrides) -> claw.Args:
    """Size I on reach with a planner and batch small enough for seconds-long runs."""
    base = dict(
        family="reach",
        model_size="I",
        rank=2,
        total_timesteps=640,
        seed_steps=100,
        burst_updates=5,
        batch_size=16,
        num_samples=32,
        num_elites=8,
        num_pi_trajs=4,
        iterations=2,
        context_pool_episodes=2,
        context_episodes=1,
        online_eval_steps=100,
        eval_episodes=1,
        log_every=20,
        checkpoint_every=10_000,
        cuda=False,
        run_dir=str(tmp_path / "run"),
        evaluate_after_training=False,
    )
    base.update(overrides)
    return claw.Args(**base)


def build(obs_dim=24, act_dim=6, size="F", rank=8, seed=0):
    torch.manual_seed(seed)
    args = claw.Args(model_size=size, rank=rank)
    model = claw.WorldModel(obs_dim, act_dim, size, args)
    layout, n_wm, n_pi = claw.lora_layout(model, rank)
    hypernet = claw.Hypernet(2 * obs_dim + act_dim + 1, claw.lora_template(layout, n_wm + n_pi), args)
    return args, model, hypernet, layout, n_wm, n_pi


def synthetic_batch(obs_dim=24, act_dim=6, batch=32, horizon=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(horizon + 1, batch, obs_dim, generator=g)
    action = torch.rand(horizon, batch, act_dim, generator=g) * 2 - 1
    reward = torch.rand(horizon, batch, 1, generator=g)
    context = torch.randn(64, 2 * obs_dim + act_dim + 1, generator=g)
    return obs, action, reward, context


@pytest.mark.parametrize("size", list(PAPER_PARAMS))
def test_parameter_counts_match_paper(size):
    model = claw.WorldModel(24, 6, size, claw.Args())
    assert sum(p.numel() for p in model.base_parameters()) == PAPER_PARAMS[size]


@pytest.mark.parametrize("rank, percent", [(1, 2.25), (2, 4.50), (4, 9.00), (8, 17.99), (16, 35.98), (32, 71.97)])
def test_adapter_counts_size_f(rank, percent):
    model = claw.WorldModel(24, 6, "F", claw.Args())
    _, n_wm, n_pi = claw.lora_layout(model, rank)
    assert n_wm == 1200 * rank  # paper Table "rank sweep"
    assert n_pi == 224 * rank
    world_model_params = sum(p.numel() for p in model.base_parameters()) - sum(p.numel() for p in model.policy.parameters())
    assert world_model_params == 53_359 and round(100 * n_wm / world_model_params, 2) == percent


def test_zero_adapter_update_at_init_leaves_base_output_unchanged():
    args, model, hypernet, layout, _, _ = build()
    model.eval()
    obs, action, _, context = synthetic_batch()
    with torch.no_grad():
        adapted = claw.adapted_weights(model, hypernet(context), layout)
        base = model.base_weights()
        for weights in (adapted, base):
            z = model.encode(obs[0], weights)
            weights["out"] = (
                z,
                model.next(z, action[0], weights),
                model.reward_logits(z, action[0], weights),
                model.Q(z, action[0], weights, "all"),
            )
    for a, b in zip(adapted["out"], base["out"]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # ...but the template is not all zeros: the random factor is what lets gradient through
    assert hypernet.template.abs().sum() > 0


def test_hypernet_receives_gradient_from_first_update():
    args, model, hypernet, layout, n_wm, _ = build()
    optimizers = claw.make_optimizers(model, hypernet, args)
    scale = claw.RunningScale(args.tau, "cpu")
    obs, action, reward, context = synthetic_batch()
    template_before = hypernet.template.detach().clone()
    generator_before = hypernet.generator[-1].weight.detach().clone()
    # phase 1 alone: the world-model loss must reach the template and the generator's last layer
    phi = hypernet(context)
    loss, _, _ = claw.world_model_loss(model, claw.adapted_weights(model, phi, layout), obs, action, reward, 0.99, args)
    loss.backward()
    assert hypernet.template.grad[:n_wm].abs().sum() > 0
    assert hypernet.generator[-1].weight.grad.abs().sum() > 0
    hypernet.zero_grad()
    claw.update(model, hypernet, optimizers, scale, layout, n_wm, obs, action, reward, context, 0.99, args)
    assert not torch.equal(hypernet.template, template_before)
    assert not torch.equal(hypernet.generator[-1].weight, generator_before)
    # after one step the generator is no longer zero, so the context encoder gets gradient too
    claw.update(model, hypernet, optimizers, scale, layout, n_wm, obs, action, reward, context, 0.99, args)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in hypernet.encoder.parameters())


def test_target_critic_tracks_base_weights_only():
    args, model, hypernet, layout, n_wm, _ = build()
    optimizers = claw.make_optimizers(model, hypernet, args)
    before = [p.clone() for p in model.target_qs.parameters()]
    claw.update(model, hypernet, optimizers, claw.RunningScale(args.tau, "cpu"), layout, n_wm, *synthetic_batch(), 0.99, args)
    for old, target, online in zip(before, model.target_qs.parameters(), model.qs.parameters()):
        torch.testing.assert_close(target, torch.lerp(old, online.detach(), args.tau))


def test_two_hot_round_trip():
    args = claw.Args()
    x = torch.tensor([[-500.0], [-3.7], [-0.2], [0.0], [0.05], [1.0], [42.0], [1000.0]])
    target = claw.two_hot(x, args)
    assert torch.allclose(target.sum(-1), torch.ones(len(x)))
    assert ((target > 0).sum(-1) <= 2).all()
    decoded = claw.two_hot_inv(torch.log(target.clamp_min(1e-30)), args)
    torch.testing.assert_close(decoded, x, rtol=1e-4, atol=1e-4)


def test_mppi_action_in_bounds():
    args, model, hypernet, layout, _, _ = build(obs_dim=39, act_dim=4)
    args.num_samples, args.num_elites, args.num_pi_trajs = 64, 8, 4
    model.eval()
    with torch.no_grad():
        weights = claw.adapted_weights(model, hypernet(torch.randn(50, 2 * 39 + 4 + 1)), layout)
    mean = None
    for step in range(5):
        action, mean = claw.plan(model, weights, torch.randn(39) * 5, mean, 0.99, args, explore=True)
        assert action.shape == (4,) and action.abs().max() <= 1 and mean.shape == (args.horizon, 4)


def test_same_seed_gives_identical_losses():
    losses = []
    for _ in range(2):
        args, model, hypernet, layout, n_wm, _ = build(seed=3)
        optimizers = claw.make_optimizers(model, hypernet, args)
        scale = claw.RunningScale(args.tau, "cpu")
        torch.manual_seed(3)
        run = [
            claw.update(model, hypernet, optimizers, scale, layout, n_wm, *synthetic_batch(seed=s), 0.99, args)
            for s in range(3)
        ]
        losses.append([float(info[k]) for info in run for k in ("wm_loss", "pi_loss", "adapter_norm")])
    assert losses[0] == losses[1]


def test_bad_arguments_give_clear_errors(tmp_path):
    with pytest.raises(SystemExit, match="unknown family 'hopper'; valid families: walker, reach"):
        claw.main(tiny_args(tmp_path, family="hopper"))
    with pytest.raises(SystemExit, match="--rank must be a positive integer"):
        claw.main(tiny_args(tmp_path, rank=0))
    with pytest.raises(SystemExit, match="does not exist"):
        claw.main(tiny_args(tmp_path, checkpoint=str(tmp_path / "missing.pt"), eval_only=True))


def test_dry_run_prints_exact_counts(tmp_path, capsys):
    claw.main(tiny_args(tmp_path, family="cheetah_walker", model_size="F", rank=8, dry_run=True))
    out = capsys.readouterr().out
    assert "base parameters: 60667\n" in out
    assert "adapter parameters: 9600 (world model) + 1792 (policy)\n" in out
    assert not os.path.exists(tmp_path / "run")


def test_same_seed_runs_are_identical_and_resume_continues(tmp_path, capsys, monkeypatch):
    claw.main(tiny_args(tmp_path / "a"))
    claw.main(tiny_args(tmp_path / "b"))
    first = torch.load(tmp_path / "a" / "run" / "checkpoint.pt", weights_only=False)
    second = torch.load(tmp_path / "b" / "run" / "checkpoint.pt", weights_only=False)
    assert first["global_step"] == 640
    for key, value in first["model"].items():
        assert torch.equal(value, second["model"][key]), key
    # a 680-step run killed at step 680's progress line: its periodic checkpoint waits for the episode end at 700,
    # so its last one is the one after the burst (step 600); its events reach 660
    args = tiny_args(tmp_path / "c", total_timesteps=680, checkpoint_every=640)
    progress_text = claw.progress_text

    def killed_at_680(step, *rest):
        if step == 680:
            raise KeyboardInterrupt
        return progress_text(step, *rest)

    monkeypatch.setattr(claw, "progress_text", killed_at_680)
    with pytest.raises(KeyboardInterrupt):
        claw.main(args)
    monkeypatch.undo()
    out = capsys.readouterr().out
    assert "budget: 680 agent steps: a 600-step random prefill, 5 burst updates" in out
    assert "step 660/680 |" in out and "| SPS " in out and "| elapsed 0:00:" in out and "| ETA 0:00:" in out
    checkpoint = os.path.join(args.run_dir, "checkpoint.pt")
    assert torch.load(checkpoint, weights_only=False)["global_step"] == 600
    # --resume alone: the saved arguments, continued from step 600 into the same run directory
    claw.main(claw.Args(resume=checkpoint))
    out = capsys.readouterr().out
    assert "at step 600" in out and "step 620/680" in out and "step 680/680" in out and "prefilled" not in out
    resumed = torch.load(checkpoint, weights_only=False)
    assert resumed["global_step"] == 680 and resumed["args"]["model_size"] == "I"
    assert resumed["replay"]["size"] == first["replay"]["size"] + 40
    # purge_step: the steps after the checkpoint were logged twice, TensorBoard keeps the resumed ones only
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(args.run_dir).Reload()
    steps = [e.step for e in events.Scalars("losses/wm_loss")]
    assert steps == [620, 640, 660, 680]


def test_end_to_end_pretraining_and_both_protocols(tmp_path, capsys):
    args = tiny_args(tmp_path, evaluate_after_training=True, eval_env_ids=(0, 5))  # two of the six goals
    claw.main(args)
    out = capsys.readouterr().out
    assert out.count("eval env") == 2 and "eval offline: return" in out
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(args.run_dir).Reload()
    tags = set(events.Tags()["scalars"])
    assert {
        "charts/SPS",
        "losses/wm_loss",
        "losses/adapter_norm",
        "eval/online/episodic_return",
        "eval/offline/episodic_return",
        "eval/online/env5/episodic_return",
    } <= tags
    # the checkpoint evaluates on its own
    claw.main(
        dataclasses.replace(
            args, eval_only=True, checkpoint=os.path.join(args.run_dir, "checkpoint.pt"), run_dir=str(tmp_path / "eval")
        )
    )
    assert capsys.readouterr().out.count("eval env") == 2  # the checkpoint's --eval-env-ids
    # an explicit --rank that contradicts the checkpoint's is an error, not silently replaced
    with pytest.raises(SystemExit, match="--rank 4 conflicts with 2"):
        claw.main(dataclasses.replace(args, eval_only=True, checkpoint=os.path.join(args.run_dir, "checkpoint.pt"), rank=4))


def test_context_pool_draws_whole_episodes_and_refreshes_in_turn():
    args = claw.Args(seed=1, context_pool_episodes=3, context_episodes=2, context_refresh_every=5)
    envs = [make_env("reach", env_id, seed=env_id) for env_id in range(2)]
    pool = claw.ContextPool(envs, args, "cpu")
    encoder = claw.ContextEncoder(2 * 39 + 4 + 1, args)
    pool.fill(encoder)
    assert [len(p) for p in pool.episodes] == [3, 3] and pool.collected == 6
    assert pool.sample(1).shape == (2 * episode_length("reach"), 2 * 39 + 4 + 1)  # two whole episodes
    oldest = [p[0] for p in pool.episodes]
    pool.refresh(4)  # not a multiple of 5: nothing happens
    assert pool.collected == 6
    pool.refresh(5)  # refresh 1 -> environment 1, its oldest episode replaced by a new one
    assert pool.episodes[0][0] is oldest[0] and pool.episodes[1][0] is not oldest[1] and pool.collected == 7
    assert not any(torch.equal(pool.episodes[1][-1], e) for e in pool.episodes[0] + pool.episodes[1][:-1])
    # standardisation: fixed from the initial pool, constant features only centred (no division by ~0)
    rows = torch.cat(sum(pool.episodes, []))
    assert torch.all(encoder.feature_std > 0) and torch.isfinite(encoder((rows - 1) * 2)).all()
    constant = rows.std(0) < 1e-6
    assert constant.any() and torch.all(encoder.feature_std[constant] == 1)


def test_context_pool_has_no_buffer_identity_shortcut():
    """Every environment is goal 0 (the same rewards), so only *which episodes* a pool holds tells the
    pools apart. For a randomly initialised hypernet, u_con of draws from the pool (whole episodes, as
    at test time) is as far apart between pools as within one (ratio ~1); 256-transition resamples of a
    fixed 10-episode buffer (the previous pipeline) are told apart by buffer identity alone."""
    from diagnostics.inspect_adapters import between_within

    torch.manual_seed(0)
    args, model, hypernet, *_ = build(obs_dim=39, act_dim=4, size="I", rank=2)
    pool = claw.ContextPool([make_env("reach", 0, seed=s) for s in range(3)], args, "cpu")
    pool.fill(hypernet.encoder)
    with torch.no_grad():
        draws = {(e, d): hypernet.encoder(pool.sample(e)) for e in range(3) for d in range(8)}
        fixed = [torch.cat(pool.episodes[e][:10]) for e in range(3)]
        resamples = {
            (e, d): hypernet.encoder(fixed[e][torch.randint(len(fixed[e]), (256,))]) for e in range(3) for d in range(8)
        }
    assert between_within(draws)[2] < 1.25  # measured 0.94-1.13 over three seeds
    assert between_within(resamples)[2] > 2.0  # measured 2.35-2.62


def test_merged_update_sizes_measure_what_adapted_weights_adds():
    from diagnostics.inspect_adapters import merged_update_sizes

    torch.manual_seed(0)
    args, model, hypernet, layout, *_ = build(obs_dim=39, act_dim=4, size="I", rank=2)
    model = model.double()
    phi = torch.randn(len(hypernet.template), dtype=torch.float64)
    sizes, spreads = merged_update_sizes(model, [phi, 2 * phi], layout)
    base, merged = model.base_weights(), claw.adapted_weights(model, phi, layout)
    expected = [
        float((merged[name][layer] - base[name][layer]).norm() / base[name][layer].norm()) for name, layer, *_ in layout
    ]
    assert sizes == pytest.approx(expected, rel=1e-9) and min(sizes) > 0
    assert spreads == pytest.approx([3 * s for s in sizes], rel=1e-9)  # 2 phi doubles A and B: 4 A B
    assert merged_update_sizes(model, [phi], layout)[1] == [0.0] * len(layout)


def test_discount_is_the_papers_unless_the_heuristic_is_asked_for():
    assert claw.default_discount(claw.Args(), 100) == 0.99
    assert claw.default_discount(claw.Args(discount_heuristic=True), 100) == 0.95
    assert claw.default_discount(claw.Args(discount_heuristic=True), 500) == 0.99
