"""diagnostics/context_controls.py: the own arm is CLAW's evaluation, the swapped arm feeds another environment's
context, arms are deterministic, and bad checkpoints are one-line errors."""

import json
import os
import random

import numpy as np
import pytest
import torch
from test_claw import tiny_args

import claw_tdmpc2 as claw
import common.evaluation as common_evaluation
from common.context import collect_episodes
from common.envs import make_env
from common.evaluation import offline_adaptation
from diagnostics import context_controls

N_ENVS = 6  # reach
EVAL_ENVS = [0, 1]  # the checkpoint's --eval-env-ids: every arm evaluates these two goals


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    # the smallest planner (the tests evaluate it some hundred episodes): its cost is most of this file's
    planner = dict(iterations=1, num_samples=16, num_elites=4, num_pi_trajs=2)
    args = tiny_args(tmp_path_factory.mktemp("claw"), **planner, log_every=100, compile="off", eval_env_ids=tuple(EVAL_ENVS))
    claw.main(args)
    return os.path.join(args.run_dir, "checkpoint.pt")


ARGV = ["--context-episodes", "1", "2", "--eval-episodes", "1", "--swap-offset", "2"]


@pytest.fixture(scope="module")
def uninterrupted(checkpoint, tmp_path_factory):
    """One uninterrupted run of the tool (own, swapped and 2-episode arms), its tables written: (result, directory)."""
    out = tmp_path_factory.mktemp("uninterrupted")
    argv = [checkpoint, *ARGV, "--out", str(out / "a.md"), "--json", str(out / "a.json"), "--progress", str(out / "whole")]
    return context_controls.main(argv), out


def own_context(args, env_id, episodes):
    """Computed here, not by the tool: evaluate()'s environment and context seeds."""
    env = make_env("reach", env_id, seed=args.seed + 10_000 + env_id)
    return claw.context_tensor(collect_episodes(env, episodes, seed=args.seed + 20_000 + env_id), "cpu")


def by_hand_env0(checkpoint, args):
    """Environment 0's offline return (1 episode, 1-episode context) recomputed with claw's pieces, from the random
    state that --eval-only starts evaluate() with."""
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    model = claw.WorldModel(39, 4, args.model_size, args)
    layout, n_wm, n_pi = claw.lora_layout(model, args.rank)
    hypernet = claw.Hypernet(2 * 39 + 4 + 1, claw.lora_template(layout, n_wm + n_pi), args)
    claw.load_checkpoint(checkpoint, model, hypernet)
    model.eval()
    env = make_env("reach", 0, seed=args.seed + 10_000)
    context = collect_episodes(env, 1, seed=args.seed + 20_000)
    with torch.no_grad():
        weights = claw.adapted_weights(model, hypernet(claw.context_tensor(context, "cpu")), layout)
    discount, state = claw.default_discount(args, 100), {"mean": None}

    def act(obs, first_step):
        action, state["mean"] = claw.plan(
            model,
            weights,
            torch.as_tensor(obs, dtype=torch.float32),
            None if first_step else state["mean"],
            discount,
            args,
            explore=False,
        )
        return action.numpy()

    records = offline_adaptation(env, context, lambda c: None, act, 1, seed=args.seed + 40_000)
    return records[0]["return"]


def test_own_arm_is_claws_evaluation_and_swapped_arm_feeds_the_other_context(checkpoint, monkeypatch):
    inputs, forward = [], claw.Hypernet.forward

    def spy(self, transitions):
        inputs.append(transitions.clone())
        return forward(self, transitions)

    monkeypatch.setattr(claw.Hypernet, "forward", spy)
    result = context_controls.controls(
        checkpoint, swap_offset=1, context_episodes=(1, 2), eval_episodes=1, online_eval_steps=0, log=lambda line: None
    )
    monkeypatch.setattr(claw.Hypernet, "forward", forward)
    assert result["context_episodes"] == 1 and set(result["size"]) == {1, 2}
    own, swapped = result["swap"]["own"]["offline"], result["swap"]["swapped"]["offline"]
    for column in (own, swapped, result["size"][1], result["size"][2]):
        assert sorted(column) == EVAL_ENVS and all(np.isfinite(v) for v in column.values())
    # hypernet inputs, in order: own arm, swapped arm (env j gets env (j+1) mod 6's context), the 2-episode own arm;
    # the 1-episode size arm is the own arm (same key: not run again)
    args = claw.Args(
        **{k: v for k, v in torch.load(checkpoint, weights_only=False)["args"].items() if k in claw.Args.__dataclass_fields__}
    )
    expected = (
        [own_context(args, j, 1) for j in EVAL_ENVS]
        + [own_context(args, (j + 1) % N_ENVS, 1) for j in EVAL_ENVS]
        + [own_context(args, j, 2) for j in EVAL_ENVS]
    )
    assert len(inputs) == len(expected)
    for got, want in zip(inputs, expected):
        assert torch.equal(got, want)
    assert result["size"][1] == own
    assert own != swapped and result["size"][2] != own  # other adapters: other plans, other returns
    assert own[0] == by_hand_env0(checkpoint, args)


def test_two_runs_print_identical_tables(checkpoint, uninterrupted, tmp_path, capsys):
    first, out = uninterrupted
    second = context_controls.main([checkpoint, *ARGV, "--out", str(tmp_path / "b.md")])
    assert first == second
    saved = json.loads((out / "a.json").read_text())  # the same numbers; JSON's keys are strings
    assert saved["swap"]["own"]["offline"] == {str(j): v for j, v in first["swap"]["own"]["offline"].items()}
    assert saved["size"] == {str(k): {str(j): v for j, v in column.items()} for k, column in first["size"].items()}
    assert saved["swap_offset"] == 2 and not (out / "a.json.tmp").exists()
    text = (out / "a.md").read_text()
    assert text == (tmp_path / "b.md").read_text() and text in capsys.readouterr().out
    assert text.count("| mean ± 95% CI |") == 2 and "context of env (j+2) mod 6" in text and "Exp 1 online" not in text


def test_online_protocol_own_vs_swapped(checkpoint):
    result = context_controls.controls(
        checkpoint, swap_offset=3, context_episodes=(1,), eval_episodes=1, online_eval_steps=100, log=lambda line: None
    )
    own, swapped = result["swap"]["own"]["online"], result["swap"]["swapped"]["online"]
    assert sorted(own) == sorted(swapped) == EVAL_ENVS
    assert all(np.isfinite(v) for v in [*own.values(), *swapped.values()])  # one finished 100-step episode each
    assert own != swapped
    # online steps run before the offline episodes and draw planner noise: the offline arm differs from the online-free one
    assert result["swap"]["own"]["offline"] != result["size"][1]
    assert "Exp 1 online protocol (100 steps" in context_controls.report(checkpoint, result)
    # an arm after others starts from the same random state as the first: equal to the recomputation
    args = claw.Args(
        **{k: v for k, v in torch.load(checkpoint, weights_only=False)["args"].items() if k in claw.Args.__dataclass_fields__}
    )
    assert result["size"][1][0] == by_hand_env0(checkpoint, args)


def test_one_line_errors(checkpoint, tmp_path):
    with pytest.raises(SystemExit, match="missing.pt does not exist"):
        context_controls.main([str(tmp_path / "missing.pt")])
    foreign = tmp_path / "dr.pt"
    torch.save({"args": {"family": "reach"}, "model": {}, "method": "dr_tdmpc2.py"}, foreign)
    with pytest.raises(
        SystemExit,
        match=r"is a checkpoint of DR \(dr_tdmpc2.py\); context_controls.py needs a checkpoint of CLAW \(claw_tdmpc2.py\)",
    ):
        context_controls.main([str(foreign)])
    with pytest.raises(SystemExit, match="--swap-offset 6 is a multiple of the 6 environments"):
        context_controls.main([checkpoint, "--swap-offset", "6"])


def test_an_interrupted_run_goes_on_from_its_finished_arms_and_environments(checkpoint, uninterrupted, tmp_path, monkeypatch):
    argv = [checkpoint, *ARGV]
    calls, offline = [], common_evaluation.offline_adaptation

    def killed_in_the_second_arm(*args, **kwargs):  # arm 1 runs environments 0 and 1, arm 2 is killed in environment 1
        calls.append(1)
        if len(calls) == len(EVAL_ENVS) + 2:
            raise KeyboardInterrupt
        return offline(*args, **kwargs)

    monkeypatch.setattr(common_evaluation, "offline_adaptation", killed_in_the_second_arm)
    json_path = tmp_path / "c.json"
    with pytest.raises(KeyboardInterrupt):
        context_controls.main([*argv, "--json", str(json_path)])
    assert os.path.exists(f"{json_path}.arms.pt") and not json_path.exists()
    assert [name.split("-", 2)[2] for name in os.listdir(tmp_path) if name.startswith("c.json.arm-")] == ["1-2-0.pt"]
    monkeypatch.setattr(common_evaluation, "offline_adaptation", offline)
    calls.clear()
    monkeypatch.setattr(common_evaluation, "offline_adaptation", lambda *a, **k: calls.append(1) or offline(*a, **k))
    resumed = context_controls.main([*argv, "--json", str(json_path)])
    assert resumed == uninterrupted[0]
    assert len(calls) == (len(EVAL_ENVS) - 1) + len(EVAL_ENVS)  # the rest of arm 2, then the 2-episode arm; arm 1 not rerun
    assert sorted(os.listdir(tmp_path)) == ["c.json"]  # progress files removed once the result is written


def test_an_arm_interrupted_under_other_settings_is_not_taken_up(checkpoint, uninterrupted, tmp_path, monkeypatch):
    """Killed in the first arm (no finished arm saved yet), then rerun with another --eval-episodes: the rerun must not
    reuse the first run's finished environments, whose episodes were averaged over another count."""
    argv = [checkpoint, *ARGV]
    calls, offline = [], common_evaluation.offline_adaptation

    def killed_in_environment_1(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return offline(*args, **kwargs)

    monkeypatch.setattr(common_evaluation, "offline_adaptation", killed_in_environment_1)
    json_path = tmp_path / "c.json"
    with pytest.raises(KeyboardInterrupt):  # ARGV's --eval-episodes 1, here 2 (the last flag wins)
        context_controls.main([*argv, "--eval-episodes", "2", "--json", str(json_path)])
    assert not os.path.exists(f"{json_path}.arms.pt") and any(name.startswith("c.json.arm-") for name in os.listdir(tmp_path))
    calls.clear()
    monkeypatch.setattr(common_evaluation, "offline_adaptation", lambda *a, **k: calls.append(1) or offline(*a, **k))
    assert context_controls.main([*argv, "--json", str(json_path)]) == uninterrupted[0]
    assert len(calls) == 3 * len(EVAL_ENVS)  # own, swapped and 2-episode arms, every environment run again
    assert sorted(os.listdir(tmp_path)) == ["c.json"]
