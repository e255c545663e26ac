"""film_tdmpc2.py, concat_tdmpc2.py, posthoc_tdmpc2.py: method mechanics, counts, e2e, resume."""

import dataclasses
import os

import pytest
import torch
import torch.nn.functional as F
from test_claw import synthetic_batch

import concat_tdmpc2 as concat
import film_tdmpc2 as film
import posthoc_tdmpc2 as posthoc

TINY = dict(
    model_size="I",
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
    evaluate_after_training=False,
)


def tiny_args(module, tmp_path, **overrides):
    """Size I on reach (post-hoc: cheetah_walker) with a planner and batch small enough for seconds-long runs."""
    base = dict(TINY, family="reach", total_timesteps=640, run_dir=str(tmp_path / "run"))
    if module is posthoc:
        base.update(family="cheetah_walker", rank=2, total_timesteps=1100, log_every=25)
    base.update(overrides)
    return module.Args(**base)


def scalar_tags(run_dir) -> set:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    return set(EventAccumulator(str(run_dir)).Reload().Tags()["scalars"])


# ---------------------------------------------------------------------------------------------
# FiLM
# ---------------------------------------------------------------------------------------------
def build_film(obs_dim=24, act_dim=6, size="F", seed=0):
    torch.manual_seed(seed)
    args = film.Args(model_size=size)
    model = film.WorldModel(obs_dim, act_dim, size, args)
    layout, n_wm, n_pi = film.film_layout(model)
    hypernet = film.Hypernet(2 * obs_dim + act_dim + 1, torch.zeros(n_wm + n_pi), args)
    return args, model, hypernet, layout, n_wm, n_pi


def test_film_dry_run_counts(tmp_path, capsys):
    film.main(tiny_args(film, tmp_path, family="cheetah_walker", model_size="F", dry_run=True))
    out = capsys.readouterr().out
    assert "base parameters: 60667\n" in out
    # paper Table "rank sweep": FiLM = 1,280 = a scale and a shift per world-model hidden feature
    assert "adapter parameters: 1280 (world model) + 256 (policy)\n" in out
    assert not os.path.exists(tmp_path / "run")


def test_film_identity_at_init_and_gradient_from_first_update():
    args, model, hypernet, layout, n_wm, _ = build_film()
    model.eval()
    obs, action, reward, context = synthetic_batch()
    with torch.no_grad():
        phi = hypernet(context)
        adapted, base = film.adapted_weights(model, phi, layout), model.base_weights()
        for weights in (adapted, base):
            z = model.encode(obs[0], weights)
            weights["out"] = (
                z,
                model.next(z, action[0], weights),
                model.reward_logits(z, action[0], weights),
                model.Q(z, action[0], weights, "all"),
                model.Q(z, action[0], weights, "all", target=True),
                model.policy(z, weights["policy"]),
            )
    assert phi.abs().sum() == 0  # template zero and generator output zero: gamma = beta = 0
    for a, b in zip(adapted["out"], base["out"]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # gradient reaches gamma and beta from the first backward pass; reward and Q layers sit below
    # TD-MPC2's zero-initialised heads, so theirs follows once the heads have moved (as for LoRA)
    optimizers, scale = film.make_optimizers(model, hypernet, args), film.RunningScale(args.tau, "cpu")
    for first in (True, False):
        phi = hypernet(context)
        loss, _, _ = film.world_model_loss(model, film.adapted_weights(model, phi, layout), obs, action, reward, 0.99, args)
        hypernet.zero_grad()
        loss.backward()
        grad = hypernet.template.grad
        for name, layer, shape, offset in layout:
            size = torch.Size(shape).numel()
            if offset < n_wm and (name in ("encoder", "dynamics") or not first):
                assert grad[offset : offset + size].abs().sum() > 0, (name, layer, "gamma")
                assert grad[offset + size : offset + 2 * size].abs().sum() > 0, (name, layer, "beta")
        if first:
            assert hypernet.generator[-1].weight.grad.abs().sum() > 0
            # one full update moves both slices of the template (the policy slice through phase 2)
            before = hypernet.template.detach().clone()
            film.update(model, hypernet, optimizers, scale, layout, n_wm, obs, action, reward, context, 0.99, args)
            assert not torch.equal(hypernet.template[:n_wm], before[:n_wm])
            assert not torch.equal(hypernet.template[n_wm:], before[n_wm:])


def test_film_scales_and_shifts_layernorm_outputs():
    """h = LN(x) (1 + gamma) + beta with the module's own LayerNorm affine, on the encoder's hidden layers."""
    args, model, hypernet, layout, _, _ = build_film()
    phi = torch.randn(hypernet.num_params)
    obs = synthetic_batch()[0][0]
    with torch.no_grad():
        z = model.encode(obs, film.adapted_weights(model, phi, layout))
        enc, x = model.encoder, obs
        for layer in range(enc.num_normed):
            ((_, _, shape, offset),) = [e for e in layout if e[:2] == ("encoder", layer)]
            gamma, beta = phi[offset : offset + shape[0]], phi[offset + shape[0] : offset + 2 * shape[0]]
            x = F.layer_norm(
                F.linear(x, enc.weights[layer], enc.biases[layer]), shape, enc.norm_weights[layer], enc.norm_biases[layer]
            )
            x = x * (1 + gamma) + beta
            x = F.mish(x) if layer < enc.num_normed - 1 else torch.softmax(x.view(len(x), -1, 8), -1).view(len(x), -1)
    torch.testing.assert_close(z, x)
    # the target critic gets the same FiLM on its own LayerNorm, without gradient
    weights = film.adapted_weights(model, phi.requires_grad_(), layout)
    assert not weights["target_qs"][1][0].requires_grad and weights["qs"][1][0].requires_grad


def test_film_end_to_end_and_resume(tmp_path, capsys):
    args = tiny_args(film, tmp_path, evaluate_after_training=True, eval_env_ids=(0, 5))
    film.main(args)
    out = capsys.readouterr().out
    assert out.count("eval env") == 2 and "eval offline: return" in out
    assert {
        "charts/SPS",
        "losses/wm_loss",
        "losses/adapter_norm",
        "eval/online/episodic_return",
        "eval/offline/episodic_return",
        "eval/online/env5/episodic_return",
    } <= scalar_tags(args.run_dir)
    checkpoint = os.path.join(args.run_dir, "checkpoint.pt")
    state = torch.load(checkpoint, weights_only=False)
    state["args"].update(total_timesteps=660, evaluate_after_training=False)  # as if killed at 640 of 660
    torch.save(state, checkpoint)
    film.main(film.Args(resume=checkpoint))
    out = capsys.readouterr().out
    assert "at step 640" in out and "step 660/660" in out
    assert torch.load(checkpoint, weights_only=False)["global_step"] == 660


# ---------------------------------------------------------------------------------------------
# Concat
# ---------------------------------------------------------------------------------------------
def test_concat_encoder_input_is_obs_plus_context(tmp_path, capsys):
    model = concat.WorldModel(24, 6, "F", concat.Args())
    assert model.encoder.weights[0].shape[-1] == 24 + 64
    concat.main(tiny_args(concat, tmp_path, family="cheetah_walker", model_size="F", dry_run=True))
    out = capsys.readouterr().out
    assert f"base parameters: {60667 + 64 * 64}\n" in out  # only the encoder's first layer widens
    assert (
        "adapter parameters: 0 (world model) + 0 (policy)\ncontext encoder parameters: " in out and "(dimension 64)\n" in out
    )


def test_concat_context_conditions_latent_and_trains_end_to_end():
    torch.manual_seed(0)
    args = concat.Args(model_size="F")
    model = concat.WorldModel(24, 6, "F", args)
    encoder = concat.ContextEncoder(2 * 24 + 6 + 1, args)
    obs, action, reward, context = synthetic_batch()
    with torch.no_grad():
        z1 = model.encode(obs[0], concat.conditioned_weights(model, encoder(context)))
        z2 = model.encode(obs[0], concat.conditioned_weights(model, encoder(context * 3)))
    assert z1.shape == (32, 32) and not torch.allclose(z1, z2)
    before = [p.detach().clone() for p in encoder.parameters()]
    info = concat.update(
        model,
        encoder,
        concat.make_optimizers(model, encoder, args),
        concat.RunningScale(args.tau, "cpu"),
        obs,
        action,
        reward,
        context,
        0.99,
        args,
    )
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in encoder.parameters())
    assert all(not torch.equal(a, b) for a, b in zip(before, encoder.parameters()))
    assert "context_norm" in info and "adapter_norm" not in info


def test_concat_end_to_end_and_eval_only(tmp_path, capsys):
    args = tiny_args(concat, tmp_path, eval_env_ids=(0, 5))
    concat.main(args)
    assert {"charts/SPS", "losses/wm_loss", "losses/context_norm"} <= scalar_tags(args.run_dir)
    capsys.readouterr()
    eval_dir = tmp_path / "eval"
    eval_args = dataclasses.replace(
        args, eval_only=True, checkpoint=os.path.join(args.run_dir, "checkpoint.pt"), run_dir=str(eval_dir)
    )
    with pytest.raises(SystemExit, match="--context-dim 1 conflicts with 64"):  # never silently replaced
        concat.main(dataclasses.replace(eval_args, context_dim=1))
    concat.main(eval_args)
    out = capsys.readouterr().out
    assert out.count("eval env") == 2 and "eval offline: return" in out
    assert {
        "eval/online/episodic_return",
        "eval/offline/episodic_return",
        "eval/online/env5/episodic_return",
        "eval/offline/env0/success",
    } <= scalar_tags(eval_dir)


# ---------------------------------------------------------------------------------------------
# Post-hoc
# ---------------------------------------------------------------------------------------------
def test_posthoc_bad_arguments(tmp_path):
    with pytest.raises(SystemExit, match="post-hoc needs --family cheetah_walker .*got 'reach'"):
        posthoc.main(tiny_args(posthoc, tmp_path, family="reach"))
    with pytest.raises(SystemExit, match="unknown family 'hopper'"):
        posthoc.main(tiny_args(posthoc, tmp_path, family="hopper"))
    with pytest.raises(SystemExit, match="--rank must be a positive integer"):
        posthoc.main(tiny_args(posthoc, tmp_path, rank=0))
    defaults = posthoc.Args()
    assert (defaults.family, defaults.model_size, defaults.rank) == ("cheetah_walker", None, 8)  # None: A on CUDA, F on a CPU
    assert posthoc.DEFAULT_TOTAL_TIMESTEPS["cheetah_walker"] == 500_000


def test_posthoc_passes_train_only_their_own_parameters():
    torch.manual_seed(0)
    args = posthoc.Args(model_size="I", rank=2)
    model = posthoc.WorldModel(24, 6, "I", args)
    layout, n_wm, n_pi = posthoc.lora_layout(model, args.rank)
    hypernet = posthoc.Hypernet(2 * 24 + 6 + 1, posthoc.lora_template(layout, n_wm + n_pi), args)
    optimizers, scale = posthoc.make_optimizers(model, hypernet, args), posthoc.RunningScale(args.tau, "cpu")
    obs, action, reward, context = synthetic_batch()
    snapshot = lambda module: {k: v.clone() for k, v in module.state_dict().items()}  # noqa: E731
    # pass 1: plain TD-MPC2, the hypernet is not in the loss
    model_before, hyper_before = snapshot(model), snapshot(hypernet)
    info = posthoc.update(model, hypernet, optimizers, scale, layout, n_wm, obs, action, reward, None, 0.99, args)
    assert torch.isnan(info["adapter_norm"])
    assert all(torch.equal(v, hypernet.state_dict()[k]) for k, v in hyper_before.items())
    assert not torch.equal(model_before["encoder.weights.0"], model.encoder.weights[0])
    assert not torch.equal(model_before["target_qs.weights.2"], model.target_qs.weights[2])  # EMA of the base
    # pass 2: base and target critic frozen, only the hypernet moves
    model.requires_grad_(False)
    model_before, hyper_before = snapshot(model), snapshot(hypernet)
    for _ in range(2):
        posthoc.update(model, hypernet, optimizers, scale, layout, n_wm, obs, action, reward, context, 0.99, args)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in model_before.items())
    assert not torch.equal(hyper_before["template"], hypernet.template)


def test_posthoc_resume_across_pass_boundary_freezes_base_and_evaluates_cheetah(tmp_path, capsys, monkeypatch):
    # a run killed right after pass 1 (its checkpoint at total/2 = 550 is the last one written)
    args = tiny_args(posthoc, tmp_path, checkpoint_every=550, evaluate_after_training=True, online_eval_steps=500)

    def killed(*_, **__):
        raise KeyboardInterrupt

    monkeypatch.setattr(posthoc, "collect_episodes", killed)  # pass 2 starts by collecting cheetah context
    with pytest.raises(KeyboardInterrupt):
        posthoc.main(args)
    monkeypatch.undo()
    out = capsys.readouterr().out
    assert "pass 1: prefilled up to step 500" in out and "step 550/1100" in out and "pass 2" not in out
    checkpoint = os.path.join(args.run_dir, "checkpoint.pt")
    pass1 = torch.load(checkpoint, weights_only=False)
    assert (pass1["global_step"], pass1["pass"], pass1["contexts"]) == (550, 1, ([[]], 0))
    # resume: pass 2 with its own cheetah prefill and context pool, then cheetah-only evaluation
    posthoc.main(posthoc.Args(resume=checkpoint))
    out = capsys.readouterr().out
    assert "at step 550 in pass 1" in out and "pass 2: prefilled up to step 1050" in out and "step 1100/1100" in out
    assert out.count("eval env") == 1 and "eval env 0:" in out
    pass2 = torch.load(checkpoint, weights_only=False)
    assert (pass2["global_step"], pass2["pass"], len(pass2["contexts"][0]), len(pass2["contexts"][0][0])) == (1100, 2, 1, 2)
    assert pass2["replay"]["size"] == 1100 and len(pass2["replay"]["starts"][posthoc.CHEETAH]) > 0
    for key, value in pass1["model"].items():  # every base parameter and the target critic, bit for bit
        assert torch.equal(value, pass2["model"][key]), key
    assert not torch.equal(pass1["hypernet"]["template"], pass2["hypernet"]["template"])
    assert {
        "losses/adapter_norm",
        "eval/online/episodic_return",
        "eval/offline/episodic_return",
        "eval/online/env0/episodic_return",
    } <= scalar_tags(args.run_dir)
    # a run killed inside pass 2 continues pass 2: no new prefill, base still frozen
    state = torch.load(checkpoint, weights_only=False)
    state["args"].update(total_timesteps=1120, evaluate_after_training=False)  # as if killed at 1100 of 1120
    torch.save(state, checkpoint)
    posthoc.main(posthoc.Args(resume=checkpoint))
    out = capsys.readouterr().out
    assert "at step 1100 in pass 2" in out and "prefilled" not in out and "step 1120/1120" in out
    resumed = torch.load(checkpoint, weights_only=False)
    assert resumed["replay"]["size"] == 1120
    for key, value in pass1["model"].items():
        assert torch.equal(value, resumed["model"][key]), key


# ---------------------------------------------------------------------------------------------
# --decoder-coef (not in the paper), the same code in the four scripts with a context encoder
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("script", ["claw", "film", "concat", "posthoc"])
def test_decoder_coef_gives_the_context_encoder_a_gradient_of_its_own(script):
    import claw_tdmpc2 as claw

    module = {"claw": claw, "film": film, "concat": concat, "posthoc": posthoc}[script]
    obs, action, reward, context = synthetic_batch()

    def build(decoder_coef):
        torch.manual_seed(0)
        args = module.Args(model_size="I", decoder_coef=decoder_coef, **({"rank": 2} if module in (claw, posthoc) else {}))
        model = module.WorldModel(24, 6, "I", args)
        if module is concat:
            hypernet = concat.ContextEncoder(2 * 24 + 6 + 1, args)
            return args, model, hypernet, hypernet, ()
        layout, n_wm, n_pi = film.film_layout(model) if module is film else module.lora_layout(model, args.rank)
        template = torch.zeros(n_wm + n_pi) if module is film else module.lora_template(layout, n_wm + n_pi)
        hypernet = module.Hypernet(2 * 24 + 6 + 1, template, args)
        return args, model, hypernet, hypernet.encoder, (layout, n_wm)

    def update(args, model, hypernet, layout_args):
        optimizers = module.make_optimizers(model, hypernet, args)
        return module.update(
            model,
            hypernet,
            optimizers,
            module.RunningScale(args.tau, "cpu"),
            *layout_args,
            obs,
            action,
            reward,
            context,
            0.99,
            args,
        )

    args, model, hypernet, encoder, layout_args = build(0.0)
    assert encoder.reward_decoder is None and "decoder_loss" not in update(args, model, hypernet, layout_args)
    args, model, hypernet, encoder, layout_args = build(1.0)
    # the decoder's loss alone reaches every parameter of the encoder, also where the generator is still zero
    encoder.decoder_loss(encoder(context), obs, action, reward).backward()
    assert all(p.grad is not None and p.grad.any() for p in encoder.parameters())
    encoder.zero_grad()
    decoder_before = [p.detach().clone() for p in encoder.reward_decoder.parameters()]
    info = update(args, model, hypernet, layout_args)
    assert float(info["decoder_loss"]) > 0
    assert not any(torch.equal(a, b) for a, b in zip(decoder_before, encoder.reward_decoder.parameters()))
    with pytest.raises(SystemExit, match="--decoder-coef must be >= 0"):
        module.validate_args(module.Args(decoder_coef=-1.0))
