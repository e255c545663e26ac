"""--compile: the compiled update and planner agree with the eager ones (CPU inductor; one compile each, ~1-2 min)."""

import copy

import pytest
import torch
import torch._inductor.config
from test_claw import build, synthetic_batch

import claw_tdmpc2 as claw
import dr_tdmpc2 as dr


@pytest.fixture
def eager_random_numbers():
    """Compiled random ops (dropout, randn, randperm, multinomial) draw from torch's generator as the eager ones
    do, so that one seed gives both the same numbers; by default inductor uses its own generator."""
    with torch._inductor.config.patch(fallback_random=True):
        yield
    torch._dynamo.reset()


def parameters_and_grads(*modules):
    return [
        (name, p.detach().clone(), None if p.grad is None else p.grad.clone())
        for module in modules
        for name, p in module.named_parameters()
    ]


def test_compiled_update_matches_eager(eager_random_numbers):
    """CLAW's two-phase update (world model + hypernet, policy + hypernet, target EMA): same losses, gradients and
    updated parameters from the same batch, seed and starting point, three updates in a row (Adam moments too)."""
    args, model, hypernet, layout, n_wm, _ = build(size="I", rank=2)
    args.batch_size = 16
    runs = {}
    for mode in ("eager", "compiled"):
        m, h = copy.deepcopy(model), copy.deepcopy(hypernet)
        optimizers, scale = claw.make_optimizers(m, h, args), claw.RunningScale(args.tau, "cpu")
        update = claw.compiled(claw.update, torch.device("cpu")) if mode == "compiled" else claw.update
        torch.manual_seed(0)
        infos = [
            update(m, h, optimizers, scale, layout, n_wm, *synthetic_batch(batch=16, seed=i), 0.99, args) for i in range(3)
        ]
        runs[mode] = infos, parameters_and_grads(m, h), scale.value.clone()
    (eager_infos, eager_params, eager_scale), (compiled_infos, compiled_params, compiled_scale) = (
        runs["eager"],
        runs["compiled"],
    )
    for eager_info, compiled_info in zip(eager_infos, compiled_infos):
        for key in ("consistency_loss", "reward_loss", "value_loss", "wm_loss", "pi_loss", "grad_norm"):
            torch.testing.assert_close(compiled_info[key], eager_info[key], rtol=1e-4, atol=1e-6, msg=key)
    moved = 0
    for (name, eager_p, eager_g), (_, compiled_p, compiled_g), (_, start, _) in zip(
        eager_params, compiled_params, parameters_and_grads(model, hypernet)
    ):
        torch.testing.assert_close(compiled_p, eager_p, rtol=1e-4, atol=1e-6, msg=name)
        if eager_g is not None:
            scale = float(eager_g.abs().max())  # float32 sums in another order: ~1e-5 of the largest entry after 3 updates
            torch.testing.assert_close(compiled_g, eager_g, rtol=1e-3, atol=1e-4 * scale + 1e-9, msg=f"grad of {name}")
        moved += int(not torch.equal(eager_p, start))
    assert moved > 10  # the updates changed the parameters, so the comparison compared something
    torch.testing.assert_close(compiled_scale, eager_scale)


def test_compiled_planner_matches_eager(eager_random_numbers):
    """DR's MPPI call on the same weights and RNG state: the same action and warm-start mean, first and later steps."""
    torch.manual_seed(0)
    # the iterations unroll into the compiled graph: two carry the elites from one to the next, and compile faster than more
    args = dr.Args(model_size="I", num_samples=64, num_elites=8, num_pi_trajs=4, iterations=2)
    model = dr.WorldModel(24, 6, "I", args).eval()
    with torch.no_grad():  # non-zero heads, so that values differ between samples and the elites are not ties
        model.reward.weights[-1].normal_(0, 0.5)
        model.qs.weights[-1].normal_(0, 0.5)
    plan, weights = dr.compiled(dr.plan, torch.device("cpu")), model.base_weights()
    obs = torch.randn(2, 24)
    for explore in (False, True):
        eager_mean = compiled_mean = None
        for step in range(2):
            torch.manual_seed(step)
            eager_action, eager_mean = dr.plan(model, weights, obs[step], eager_mean, 0.99, args, explore)
            torch.manual_seed(step)
            compiled_action, compiled_mean = plan(model, weights, obs[step], compiled_mean, 0.99, args, explore)
            torch.testing.assert_close(compiled_action, eager_action, rtol=1e-4, atol=1e-5)
            torch.testing.assert_close(compiled_mean, eager_mean, rtol=1e-4, atol=1e-5)
    assert not torch.equal(eager_action, torch.zeros_like(eager_action))
