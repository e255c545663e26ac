"""diagnostics/oracle_controls.py: the own arm sees what the Oracle is evaluated on, the swapped arm another environment's
parameter on the same physics, arms are paired and deterministic, interrupted runs are taken up, bad input is one line."""

import json
import os

import numpy as np
import pytest
import torch
from test_baselines_gradient import tiny_args

import oracle_tdmpc2 as oracle
from common.envs import env_param, make_env
from diagnostics import oracle_controls

N_ENVS = 6  # reach


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    args = tiny_args(oracle, tmp_path_factory.mktemp("oracle"))
    oracle.main(args)
    return os.path.join(args.run_dir, "checkpoint.pt")


def test_told_env_keeps_the_physics_and_replaces_only_the_parameter():
    own, told, plain = (
        oracle_controls.told_env("reach", 2, 2, seed=5),
        oracle_controls.told_env("reach", 2, 4, seed=5),
        make_env("reach", 2, oracle=True, seed=5),
    )
    rng = np.random.default_rng(0)
    obs = [env.reset(seed=5)[0] for env in (own, told, plain)]
    for _ in range(20):
        np.testing.assert_array_equal(obs[0], obs[2])  # own arm: exactly the Oracle's evaluation environment
        np.testing.assert_array_equal(obs[1][:-3], obs[0][:-3])  # same physics, same trajectory
        np.testing.assert_array_equal(obs[1][-3:], env_param("reach", 4))
        action = rng.uniform(-1, 1, 4).astype(np.float32)
        obs = [env.step(action)[0] for env in (own, told, plain)]


def test_arms_feed_the_planner_own_and_told_parameters_and_are_paired(checkpoint, monkeypatch):
    seen = []

    def spy(model, weights, obs, *rest, **kw):
        seen.append(obs[-3:].clone())
        return oracle.plan(model, weights, obs, *rest, **kw)

    result = oracle_controls.controls(
        checkpoint, swap_offset=2, env_ids=[1, 5], eval_episodes=1, plan=spy, log=lambda line: None
    )
    assert list(result["envs"]) == [1, 5] and [r["told"] for r in result["envs"].values()] == [3, 1]
    assert all(np.isfinite([r["own"], r["swapped"]]).all() for r in result["envs"].values())
    per_arm = len(seen) // 4  # 100-step episodes, one planner call each step
    assert per_arm == 100
    for arm, told in enumerate([1, 3, 5, 1]):  # env 1 own, env 1 told 3, env 5 own, env 5 told 1
        for obs_param in seen[arm * per_arm : (arm + 1) * per_arm]:
            np.testing.assert_array_equal(obs_param.numpy(), env_param("reach", told))
    loaded = oracle_controls.load(checkpoint)
    again = oracle_controls.arm_return(loaded, oracle.plan, 1, 3, 1)
    assert again == result["envs"][1]["swapped"]  # deterministic: same seeds, same return
    assert oracle_controls.arm_return(loaded, oracle.plan, 1, 1, 1) == result["envs"][1]["own"]


def test_interrupted_run_is_taken_up_and_other_settings_start_afresh(checkpoint, tmp_path, monkeypatch):
    path, calls = str(tmp_path / "controls.json"), []
    arm_return = oracle_controls.arm_return

    def counting(loaded, plan, env_id, told_id, episodes):
        calls.append(env_id)
        return arm_return(loaded, plan, env_id, told_id, episodes)

    monkeypatch.setattr(oracle_controls, "arm_return", counting)
    first = oracle_controls.controls(checkpoint, 1, [0], 1, json_path=path, log=lambda line: None)
    assert calls == [0, 0] and json.load(open(path))["envs"]["0"] == first["envs"][0]
    lines = []
    second = oracle_controls.controls(checkpoint, 1, [0, 2], 1, json_path=path, log=lines.append)
    assert calls == [0, 0, 2, 2] and second["envs"][0] == first["envs"][0] and "taking up 1" in lines[0]
    oracle_controls.controls(checkpoint, 1, [0], 2, json_path=path, log=lines.append)  # other --eval-episodes
    assert calls == [0, 0, 2, 2, 0, 0] and any(line.startswith("ignoring") for line in lines)
    assert "mean ± CI" in oracle_controls.report(second)


def test_bad_input_is_one_line(checkpoint, tmp_path):
    with pytest.raises(SystemExit, match="tells every environment its own parameter"):
        oracle_controls.controls(checkpoint, N_ENVS, None, 1)
    with pytest.raises(SystemExit, match=r"--env-ids \[6\] outside the 6 environments"):
        oracle_controls.controls(checkpoint, 1, [6], 1)
    other = tmp_path / "dr.pt"
    state = torch.load(checkpoint, weights_only=False)
    torch.save({**state, "method": "dr_tdmpc2.py"}, other)
    with pytest.raises(SystemExit, match=r"oracle_controls.py needs a checkpoint of Oracle \(oracle_tdmpc2.py\)"):
        oracle_controls.controls(str(other), 1, None, 1)
    with pytest.raises(SystemExit, match="^error: --eval-episodes must be >= 1, got 0$"):
        oracle_controls.main([checkpoint, "--eval-episodes", "0"])
