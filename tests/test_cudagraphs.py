"""--cudagraphs: the flag's checks, the argument binding of graphed() (on a machine without CUDA, where CudaGraphModule
runs the function as it is, and on a GPU) and Adam's capturable setting; on a GPU also the recorded and replayed update,
test-time gradient step and planner against the eager ones over several replays (skipped without CUDA)."""

import copy
import warnings

import pytest
import torch
from test_claw import build, synthetic_batch

import claw_tdmpc2 as claw
import dr_tdmpc2 as dr
import posthoc_tdmpc2 as posthoc

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
# without CUDA the graphed functions run the plain ones: bit for bit; a replay runs the same kernels: float tolerance
SAME = dict(rtol=0, atol=0) if DEVICE == "cpu" else dict(rtol=1e-5, atol=1e-6)


def on(device, *tensors):
    return [t.to(device) for t in tensors]


def quiet(fn, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return fn(*args)


@pytest.mark.parametrize("script", [claw, dr, posthoc], ids=lambda s: s.__name__)
def test_cudagraphs_needs_cuda_and_a_gpu(script, tmp_path):
    family = "cheetah_walker" if script is posthoc else "reach"
    args = script.Args(family=family, cudagraphs=True, cuda=False, run_dir=str(tmp_path / "run"))
    with pytest.raises(SystemExit, match=r"^error: --cudagraphs needs --cuda and a GPU \(--no-cuda was given\)"):
        script.main(args)
    if not torch.cuda.is_available():
        args = script.Args(family=family, cudagraphs=True, cuda=True, run_dir=str(tmp_path / "run"))
        with pytest.raises(SystemExit, match=r"\(CUDA is not available here\)"):
            script.main(args)
    assert not (tmp_path / "run").exists()


def test_graphed_binds_what_a_replay_cannot_take_anew():
    """One graph per kind of call: the non-tensor arguments and the tensors that require gradients are bound (a new
    model, a missing warm-start mean, another explore flag: another graph), other tensors are copied in (new values of
    the same shape: the same graph). The results are eager's."""
    args = dr.Args(model_size="I", num_samples=32, num_elites=4, num_pi_trajs=4, iterations=2)
    torch.manual_seed(0)
    model = dr.WorldModel(24, 6, "I", args).to(DEVICE)
    plan = quiet(dr.graphed, dr.plan)
    obs, mean, eager_mean = torch.randn(4, 24, device=DEVICE), None, None
    for step in range(4):
        torch.manual_seed(step)
        action, mean = quiet(plan, model, model.base_weights(), obs[step], mean, 0.99, args, True)
        torch.manual_seed(step)
        eager_action, eager_mean = dr.plan(model, model.base_weights(), obs[step], eager_mean, 0.99, args, True)
        torch.testing.assert_close(action, eager_action, **SAME)
        torch.testing.assert_close(mean, eager_mean, **SAME)
    quiet(plan, model, model.base_weights(), obs[0], None, 0.99, args, False)
    quiet(plan, copy.deepcopy(model), model.base_weights(), obs[0], None, 0.99, args, False)
    with torch.no_grad():  # merged weights: fresh tensors without gradients, copied in, one graph for all of them
        for scale in (1.0, 2.0):
            weights = {k: [w * scale for w in ws] for k, ws in model.base_weights().items()}
            quiet(plan, model, weights, obs[0], None, 0.99, args, False)
    # explore True: first step and later steps; explore False: two models (ids), merged weights (copied)
    assert len(plan.graphs) == 5
    assert quiet(dr.graphed, plan) is plan  # main() run twice in one process


def test_graphed_update_and_gradient_step_run_the_same_updates():
    """CLAW's two-phase update, post-hoc's two passes (no context in pass 1) and DR's test-time step on phi (a bound
    tensor) through graphed(): the same updates as the plain functions."""
    args, model, hypernet, layout, n_wm, _ = build(size="I", rank=2)
    args.batch_size = 16
    model, hypernet, runs = model.to(DEVICE), hypernet.to(DEVICE), []
    for fn in (claw.update, quiet(claw.graphed, claw.update)):
        m, h = copy.deepcopy(model), copy.deepcopy(hypernet)
        optimizers, scale = claw.make_optimizers(m, h, args), claw.RunningScale(args.tau, DEVICE)
        claw.capturable(optimizers, DEVICE == "cuda")
        torch.manual_seed(0)
        infos = [
            quiet(fn, m, h, optimizers, scale, layout, n_wm, *on(DEVICE, *synthetic_batch(batch=16, seed=i)), 0.99, args)
            for i in range(4)
        ]
        runs.append((infos, [p.detach().clone() for p in [*m.parameters(), *h.parameters()]], scale.value.clone()))
    for eager, replayed in zip(*[run[0] for run in runs]):
        assert eager.keys() == replayed.keys()
        for key in eager:
            torch.testing.assert_close(replayed[key], eager[key], **SAME, msg=key)
    for eager, replayed in zip(runs[0][1], runs[1][1]):
        torch.testing.assert_close(replayed, eager, **SAME)
    torch.testing.assert_close(runs[1][2], runs[0][2], **SAME)

    torch.manual_seed(0)
    pargs = posthoc.Args(family="cheetah_walker", model_size="I", rank=2)
    pmodel = posthoc.WorldModel(24, 6, "I", pargs).to(DEVICE)
    players, pn_wm, pn_pi = posthoc.lora_layout(pmodel, 2)
    phyper = posthoc.Hypernet(2 * 24 + 6 + 1, posthoc.lora_template(players, pn_wm + pn_pi), pargs).to(DEVICE)
    update = quiet(posthoc.graphed, posthoc.update)
    optimizers, scale = posthoc.make_optimizers(pmodel, phyper, pargs), posthoc.RunningScale(pargs.tau, DEVICE)
    posthoc.capturable(optimizers, DEVICE == "cuda")
    obs, action, reward, pass_2_context = on(DEVICE, *synthetic_batch(batch=16))
    for context in (None, pass_2_context):
        info = quiet(update, pmodel, phyper, optimizers, scale, players, pn_wm, obs, action, reward, context, 0.99, pargs)
        assert torch.isnan(info["adapter_norm"]) == (context is None) and info["adapter_norm"].device == info["wm_loss"].device
    assert len(update.graphs) == 2

    dargs = dr.Args(model_size="I", rank=2)
    torch.manual_seed(0)
    dmodel = dr.WorldModel(24, 6, "I", dargs).to(DEVICE).requires_grad_(False)
    dlayout, dn_wm, dn_pi = dr.lora_layout(dmodel, 2)
    results = []
    for fn in (dr.adapt_step, quiet(dr.graphed, dr.adapt_step)):
        torch.manual_seed(0)
        phi = dr.lora_template(dlayout, dn_wm + dn_pi).to(DEVICE).requires_grad_(True)
        optimizer = torch.optim.Adam([phi], lr=dargs.learning_rate, capturable=DEVICE == "cuda")
        scale = dr.RunningScale(dargs.tau, DEVICE)
        for i in range(4):
            quiet(fn, dmodel, phi, optimizer, scale, dlayout, *on(DEVICE, *synthetic_batch(batch=16, seed=i)[:3]), 0.99, dargs)
        results.append(phi.detach().clone())
    torch.testing.assert_close(results[1], results[0], **SAME)


def test_capturable_follows_the_flag_also_after_a_checkpoint_is_loaded():
    """Adam's capturable setting is the run's: a checkpoint written with --cudagraphs (capturable, step counts on the
    device) loads into a run without it as a plain Adam (step counts on the host), which then steps on the CPU."""
    param = torch.nn.Parameter(torch.ones(3))
    written = torch.optim.Adam([param])
    param.grad = torch.ones(3)
    written.step()
    claw.capturable([written], True)
    assert written.param_groups[0]["capturable"] and written.state[param]["step"].device == param.device
    state = written.state_dict()
    assert state["param_groups"][0]["capturable"]
    resumed = torch.optim.Adam([param])
    resumed.load_state_dict(state)
    assert resumed.param_groups[0]["capturable"]  # the writer's setting, until set again
    claw.capturable([resumed], False)
    assert not resumed.param_groups[0]["capturable"] and resumed.state[param]["step"].device.type == "cpu"
    resumed.step()
    assert float(resumed.state[param]["step"]) == 2.0


@cuda
def test_graphed_update_matches_eager_on_the_gpu():
    """CLAW's whole two-phase update recorded as one CUDA graph and replayed: the same losses, parameters, gradients and
    Q scale as eager from the same batches, seeds and starting point, over the plain calls, the recording and three
    replays (Adam moments and step counts on the device too)."""
    args, model, hypernet, layout, n_wm, _ = build(size="I", rank=2)
    args.batch_size = 16
    model, hypernet = model.cuda(), hypernet.cuda()
    runs = []
    for mode in ("eager", "graphed"):
        m, h = copy.deepcopy(model), copy.deepcopy(hypernet)
        optimizers, scale = claw.make_optimizers(m, h, args), claw.RunningScale(args.tau, "cuda")
        claw.capturable(optimizers, mode == "graphed")
        update = claw.graphed(claw.update) if mode == "graphed" else claw.update
        infos = []
        for i in range(6):
            torch.manual_seed(i)  # each call draws the same random numbers (dropout, Q heads, policy noise) in both modes
            infos.append(
                update(m, h, optimizers, scale, layout, n_wm, *on("cuda", *synthetic_batch(batch=16, seed=i)), 0.99, args)
            )
        grads = [p.grad.clone() for p in [*m.parameters(), *h.parameters()] if p.grad is not None]
        runs.append((infos, [p.detach().clone() for p in [*m.parameters(), *h.parameters()]], grads, scale.value.clone()))
        if mode == "graphed":
            assert len(update.graphs) == 1
    (eager_infos, eager_params, eager_grads, eager_scale), (infos, params, grads, scale) = runs
    for eager_info, info in zip(eager_infos, infos):
        for key in eager_info:
            torch.testing.assert_close(info[key], eager_info[key], rtol=1e-4, atol=1e-6, msg=key)
    for eager_p, p in zip(eager_params, params):
        torch.testing.assert_close(p, eager_p, rtol=1e-4, atol=1e-6)
    for eager_g, g in zip(eager_grads, grads):
        torch.testing.assert_close(g, eager_g, rtol=1e-3, atol=1e-4 * float(eager_g.abs().max()) + 1e-9)
    torch.testing.assert_close(scale, eager_scale)
    assert sum(not torch.equal(p, q.cuda()) for p, q in zip(eager_params, [*model.parameters(), *hypernet.parameters()])) > 10


@cuda
def test_graphed_gradient_step_and_planner_match_eager_on_the_gpu():
    """DR's test-time gradient step (phi bound to the graph) and the MPPI planner (explore or not, first step or not),
    recorded and replayed: the same adapters, actions and warm-start means as eager from the same seeds."""
    args = dr.Args(model_size="I", rank=2, num_samples=64, num_elites=8, num_pi_trajs=4, iterations=3)
    torch.manual_seed(0)
    model = dr.WorldModel(24, 6, "I", args).cuda().requires_grad_(False)
    with torch.no_grad():  # non-zero heads, so that values differ between samples and the elites are not ties
        model.reward.weights[-1].normal_(0, 0.5)
        model.qs.weights[-1].normal_(0, 0.5)
    layout, n_wm, n_pi = dr.lora_layout(model, 2)
    results = []
    for mode in ("eager", "graphed"):
        torch.manual_seed(0)
        phi = dr.lora_template(layout, n_wm + n_pi).cuda().requires_grad_(True)
        optimizer = torch.optim.Adam([phi], lr=args.learning_rate, capturable=mode == "graphed")
        scale = dr.RunningScale(args.tau, "cuda")
        step = dr.graphed(dr.adapt_step) if mode == "graphed" else dr.adapt_step
        plan = dr.graphed(dr.plan) if mode == "graphed" else dr.plan
        for i in range(6):
            torch.manual_seed(i)
            step(model, phi, optimizer, scale, layout, *on("cuda", *synthetic_batch(batch=16, seed=i)[:3]), 0.99, args)
        with torch.no_grad():
            weights = dr.adapted_weights(model, phi, layout)
        outputs, obs = [], torch.randn(6, 24, generator=torch.Generator().manual_seed(0)).cuda()
        for explore in (False, True):
            mean = None
            for i in range(6):
                torch.manual_seed(i)
                action, mean = plan(model, weights, obs[i], mean, 0.99, args, explore)
                outputs.append((action, mean))
        results.append((phi.detach().clone(), outputs))
    torch.testing.assert_close(results[1][0], results[0][0], rtol=1e-4, atol=1e-6)
    for (eager_action, eager_mean), (action, mean) in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(action, eager_action, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(mean, eager_mean, rtol=1e-4, atol=1e-5)


@cuda
def test_graphed_compiled_update_matches_eager_on_the_gpu():
    """--compile --cudagraphs: CLAW's update compiled (inductor, without its own CUDA graphs), then recorded and
    replayed, against eager over five updates (inductor drawing from torch's generator, as in test_compile.py; float sums
    in another order, hence the wider tolerance; a compile of ~1-2 min)."""
    import torch._inductor.config

    args, model, hypernet, layout, n_wm, _ = build(size="I", rank=2)
    args.batch_size = 16
    model, hypernet = model.cuda(), hypernet.cuda()
    runs = []
    with torch._inductor.config.patch(fallback_random=True):
        for mode in ("eager", "compiled-graphed"):
            m, h = copy.deepcopy(model), copy.deepcopy(hypernet)
            optimizers, scale = claw.make_optimizers(m, h, args), claw.RunningScale(args.tau, "cuda")
            claw.capturable(optimizers, mode != "eager")
            update = claw.update if mode == "eager" else claw.graphed(claw.compiled(claw.update, torch.device("cuda"), False))
            infos = []
            for i in range(5):
                torch.manual_seed(i)
                batch = on("cuda", *synthetic_batch(batch=16, seed=i))
                infos.append(update(m, h, optimizers, scale, layout, n_wm, *batch, 0.99, args))
            runs.append((infos, [p.detach().clone() for p in [*m.parameters(), *h.parameters()]]))
    torch._dynamo.reset()
    for eager_info, info in zip(runs[0][0], runs[1][0]):
        for key in eager_info:
            torch.testing.assert_close(info[key], eager_info[key], rtol=1e-3, atol=1e-5, msg=key)
    for eager_p, p in zip(runs[0][1], runs[1][1]):
        torch.testing.assert_close(p, eager_p, rtol=1e-3, atol=1e-5)
