import os

os.environ.setdefault("MUJOCO_GL", "disable")  # headless: avoid GLFW/X11 on import

import gymnasium
import numpy as np
import pytest

from common.context import collect_episodes
from common.envs import FAMILIES, env_param, episode_length, is_metaworld, make_env, num_envs, rng_state, set_rng_state

OBS_DIM = {"walker": 24, "reach": 39, "push": 39, "go1": 39, "cheetah_walker": 24}
ACT_DIM = {"walker": 6, "reach": 4, "push": 4, "go1": 12, "cheetah_walker": 6}
ORACLE_DIM = {"walker": 1, "reach": 3, "push": 3, "go1": 1, "cheetah_walker": 1}


def rollout(env, actions, seed):
    obs, _ = env.reset(seed=seed)
    traj, rewards = [obs], []
    for a in actions:
        obs, r, terminated, truncated, info = env.step(a)
        assert not terminated and isinstance(info["success"], float)
        traj.append(obs)
        rewards.append(r)
    return np.array(traj), np.array(rewards)


def random_actions(family, n, seed=0):
    return np.random.default_rng(seed).uniform(-1, 1, (n, ACT_DIM[family])).astype(np.float32)


def test_family_table():
    assert FAMILIES == ("walker", "reach", "push", "go1", "cheetah_walker")
    assert [num_envs(f) for f in FAMILIES] == [20, 6, 6, 2, 2]
    assert [episode_length(f) for f in FAMILIES] == [500, 100, 100, 1000, 500]
    assert [is_metaworld(f) for f in FAMILIES] == [False, True, True, False, False]
    assert np.allclose(env_param("walker", 0), [0.5]) and np.allclose(env_param("walker", 19), [1.5])
    assert env_param("go1", 0).tolist() == [1.0] and env_param("go1", 1).tolist() == [-1.0]
    assert env_param("cheetah_walker", 1).tolist() == [1.0]
    assert np.allclose(env_param("push", 1), [-0.1, 0.9, 0.02])
    for f in FAMILIES:
        p = env_param(f, 0)
        assert p.dtype == np.float32 and p.shape == (ORACLE_DIM[f],)


@pytest.mark.parametrize("oracle", [False, True])
@pytest.mark.parametrize("family", FAMILIES)
def test_spaces_and_oracle(family, oracle):
    env_id = num_envs(family) - 1
    env = make_env(family, env_id, oracle=oracle, seed=0)
    dim = OBS_DIM[family] + (ORACLE_DIM[family] if oracle else 0)
    assert env.observation_space.shape == (dim,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (ACT_DIM[family],) and env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, _ = env.reset()
    obs2, r, terminated, truncated, info = env.step(env.action_space.sample())
    for o in (obs, obs2):
        assert o.shape == (dim,) and o.dtype == np.float32 and np.all(np.isfinite(o))
        if oracle:
            np.testing.assert_array_equal(o[-ORACLE_DIM[family] :], env_param(family, env_id))
    assert isinstance(r, float) and not terminated and not truncated
    assert isinstance(info["success"], float)
    if not is_metaworld(family):
        assert info["success"] == 0.0


@pytest.mark.filterwarnings("ignore:.*infinity")  # unbounded state observations are intended
@pytest.mark.parametrize("family", FAMILIES)
def test_gymnasium_env_checker(family):
    from gymnasium.utils.env_checker import check_env

    check_env(make_env(family, 1).unwrapped, skip_render_check=True)


@pytest.mark.parametrize("family", FAMILIES)
def test_time_limit(family):
    env = make_env(family, 0)
    assert isinstance(env, gymnasium.wrappers.TimeLimit)
    assert env._max_episode_steps == episode_length(family)


def test_truncation_reach():
    env = make_env("reach", 0, seed=0)
    env.reset()
    flags = [env.step(np.zeros(4, np.float32))[2:4] for _ in range(episode_length("reach"))]
    assert not any(t for t, _ in flags)
    assert [tr for _, tr in flags] == [False] * 99 + [True]


@pytest.mark.parametrize("family", FAMILIES)
def test_determinism(family):
    env_id = num_envs(family) - 1
    actions = random_actions(family, 15)
    a_obs, a_rew = rollout(make_env(family, env_id, seed=3), actions, seed=None)  # seeded by make_env
    env = make_env(family, env_id)
    b_obs, b_rew = rollout(env, actions, seed=3)
    c_obs, c_rew = rollout(env, actions, seed=3)  # reset(seed=...) after use
    for obs, rew in ((b_obs, b_rew), (c_obs, c_rew)):
        np.testing.assert_array_equal(a_obs, obs)
        np.testing.assert_array_equal(a_rew, rew)
    if not is_metaworld(family):  # Meta-World starts are frozen by design; the others are noisy
        d_obs, _ = env.reset(seed=4)
        assert not np.array_equal(d_obs, a_obs[0])


def test_walker_strengths_differ():
    actions = random_actions("walker", 20)
    weak, _ = rollout(make_env("walker", 0), actions, seed=0)
    strong, _ = rollout(make_env("walker", 19), actions, seed=0)
    np.testing.assert_array_equal(weak[0], strong[0])  # same start, only dynamics differ
    assert np.abs(weak[-1] - strong[-1]).max() > 0.1
    env = make_env("walker", 19)
    for seed in (0, 1):  # the scaled gear must survive resets
        env.reset(seed=seed)
        np.testing.assert_allclose(env.unwrapped.physics.model.actuator_gear[:, 0], 1.5 * np.array([100, 50, 20, 100, 50, 20]))


def test_cheetah_padding():
    env = make_env("cheetah_walker", 0, seed=0)
    obs, _ = env.reset()
    obs2 = env.step(env.action_space.sample())[0]
    assert np.all(obs[17:] == 0) and np.all(obs2[17:] == 0) and np.any(obs2[:17] != 0)
    walker = make_env("cheetah_walker", 1, seed=0)
    walker.reset()
    assert np.any(walker.step(walker.action_space.sample())[0][17:] != 0)  # real velocities, no pad


@pytest.mark.parametrize("family", ["reach", "push"])
def test_metaworld_goal_is_only_difference(family):
    actions = random_actions(family, 5)
    trajs = [rollout(make_env(family, i), actions, seed=0)[0] for i in range(num_envs(family))]
    for t in trajs:
        np.testing.assert_array_equal(t, trajs[0])  # same obs even under the same actions
        assert np.all(t[:, 36:39] == 0)
    goals = {tuple(env_param(family, i)) for i in range(num_envs(family))}
    assert len(goals) == num_envs(family)


def _hand_to(target, hand):
    return np.clip(10.0 * (target - hand), -1, 1)


def reach_policy(goal, tcp_offset):
    def policy(obs):
        return np.append(_hand_to(goal + tcp_offset, obs[:3]), -1.0).astype(np.float32)

    return policy


def push_policy(goal):
    """Grasp the puck from above and carry it, slightly lifted, to ``goal`` (a scripted pusher)."""
    phase = {"close_steps": 0}

    def policy(obs):
        hand, puck = obs[:3], obs[4:7]
        grip_z = goal[2] + 0.045  # table-level grasp; the hand body sits ~0.045 above the fingertips
        if phase["close_steps"] == 0 and np.linalg.norm(hand[:2] - puck[:2]) > 0.01:
            target, grip = puck + [0, 0, 0.1], -1.0  # hover above the puck
        elif phase["close_steps"] < 8:
            target, grip = np.array([puck[0], puck[1], grip_z]), -1.0  # descend, then close
            if abs(hand[2] - grip_z) < 0.01:
                phase["close_steps"] += 1
                grip = 1.0
        else:
            target, grip = np.array([goal[0], goal[1], grip_z + 0.01]), 1.0  # carry to the goal
        return np.append(_hand_to(target, hand), grip).astype(np.float32)

    return policy


def run_policy(env, policy):
    obs, _ = env.reset(seed=0)
    ret, success = 0.0, 0.0
    for _ in range(episode_length("reach")):
        obs, r, _, truncated, info = env.step(policy(obs))
        ret += r
        success = info["success"]
    assert truncated
    return ret, success


def test_reach_scripted_policy_prefers_its_goal():
    target_id, other_id = 0, 5
    goal = env_param("reach", target_id).astype(np.float64)
    env = make_env("reach", target_id)
    env.reset()
    mw = env.unwrapped._mw
    tcp_offset = mw.get_endeff_pos() - mw.tcp_center  # obs reports the hand body, success uses TCP
    ret_t, succ_t = run_policy(env, reach_policy(goal, tcp_offset))
    ret_o, succ_o = run_policy(make_env("reach", other_id), reach_policy(goal, tcp_offset))
    assert succ_t == 1.0 and succ_o == 0.0
    assert ret_t > ret_o + 100


def test_push_scripted_policy_prefers_its_goal():
    target_id, other_id = 5, 0  # (0.1, 0.9) vs (-0.1, 0.8)
    goal = env_param("push", target_id).astype(np.float64)
    ret_t, succ_t = run_policy(make_env("push", target_id), push_policy(goal))
    ret_o, succ_o = run_policy(make_env("push", other_id), push_policy(goal))
    assert succ_t == 1.0 and succ_o == 0.0
    assert ret_t > 1.5 * ret_o


def test_metaworld_rejects_goal_too_close():
    from common.envs import MetaWorldEnv

    with pytest.raises(ValueError, match="0.15"):
        MetaWorldEnv("push-v3", [0.05, 0.65, 0.02])


def go1_return(env_id, push_speed, steps=10):
    env = make_env("go1", env_id, seed=0)
    env.reset()
    env.unwrapped.data.qvel[0] = push_speed  # world x = body forward at reset
    return sum(env.step(np.zeros(12, np.float32))[1] for _ in range(steps))


def test_go1_direction():
    fwd, bwd = 0, 1
    assert go1_return(fwd, 1.5) > 1.0 and go1_return(bwd, 1.5) == 0.0
    assert go1_return(bwd, -1.5) > 1.0 and go1_return(fwd, -1.5) == 0.0


def test_go1_stands_under_pd():
    env = make_env("go1", 0, seed=0)
    obs, _ = env.reset()
    assert np.all(obs[-4:] == 1)  # all four feet on the floor
    for _ in range(50):
        obs = env.step(np.zeros(12, np.float32))[0]
    assert 0.2 < obs[0] < 0.3 and obs[1] > 0.99  # height, quaternion w: still upright
    assert np.abs(obs[5:17]).max() < 0.25  # near home (Kp 35 sags ~0.17 rad under load)
    assert np.all(obs[-4:] == 1)


@pytest.mark.parametrize("bad", ["hopper", "Walker", ""])
def test_unknown_family(bad):
    for fn in (lambda: make_env(bad, 0), lambda: num_envs(bad), lambda: env_param(bad, 0), lambda: episode_length(bad)):
        with pytest.raises(ValueError, match="walker, reach, push, go1, cheetah_walker"):
            fn()


@pytest.mark.parametrize("family,env_id", [("walker", 20), ("walker", -1), ("go1", 2), ("reach", 6)])
def test_env_id_out_of_range(family, env_id):
    with pytest.raises(ValueError, match=f"0..{num_envs(family) - 1}"):
        make_env(family, env_id)
    with pytest.raises(ValueError, match=f"0..{num_envs(family) - 1}"):
        env_param(family, env_id)


def test_collect_episodes():
    env = make_env("reach", 2)
    data = collect_episodes(env, 2, seed=7)
    n = 2 * episode_length("reach")
    assert data["obs"].shape == (n, 39) and data["next_obs"].shape == (n, 39)
    assert data["action"].shape == (n, 4)
    assert data["reward"].shape == (n,) and data["success"].shape == (n,)
    for k in ("obs", "action", "reward", "next_obs", "success"):
        assert data[k].dtype == np.float32
    assert data["episode"].dtype == np.int64
    np.testing.assert_array_equal(data["episode"], np.repeat([0, 1], episode_length("reach")))
    # next_obs follows obs inside an episode; each episode starts from a reset
    same_ep = data["episode"][1:] == data["episode"][:-1]
    np.testing.assert_array_equal(data["next_obs"][:-1][same_ep], data["obs"][1:][same_ep])
    assert np.all(np.abs(data["action"]) <= 1)
    again = collect_episodes(make_env("reach", 2), 2, seed=7)
    for k in data:
        np.testing.assert_array_equal(data[k], again[k])
    other = collect_episodes(env, 1, seed=8)
    assert not np.array_equal(other["action"], data["action"][: len(other["action"])])


def test_collect_episodes_custom_policy_and_noisy_env():
    env = make_env("cheetah_walker", 0, oracle=True)
    env = gymnasium.wrappers.TimeLimit(env.env, max_episode_steps=10)  # short episodes for speed
    zero = lambda obs: np.zeros(6, np.float32)  # noqa: E731
    a = collect_episodes(env, 3, policy=zero, seed=1)
    b = collect_episodes(env, 3, policy=zero, seed=1)
    assert a["obs"].shape == (30, 25) and np.all(a["action"] == 0)
    np.testing.assert_array_equal(a["episode"], np.repeat([0, 1, 2], 10))
    np.testing.assert_array_equal(a["obs"], b["obs"])
    assert not np.array_equal(a["obs"][0], a["obs"][10])  # later resets draw fresh noise


@pytest.mark.parametrize("family", ["walker", "go1", "reach"])
def test_rng_state_continues_resets_and_action_samples(family):
    """rng_state/set_rng_state (exact resume): another instance continues the same resets and action samples."""
    env = make_env(family, 0, seed=3, oracle=True)
    env.action_space.seed(3)
    env.reset()
    state = rng_state(env)
    expected = [env.reset()[0], env.action_space.sample(), env.reset()[0]]
    other = make_env(family, 0, seed=99, oracle=True)
    other.action_space.seed(99)
    set_rng_state(other, state)
    for a, b in zip(expected, [other.reset()[0], other.action_space.sample(), other.reset()[0]]):
        np.testing.assert_array_equal(a, b)
