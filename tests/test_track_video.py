"""--track (Weights & Biases, offline) and --capture-video (Exp 2 episodes rendered through MuJoCo).

Both run a tiny dr_tdmpc2.py in a subprocess: W&B patches TensorBoard for the whole process, and
MuJoCo picks its GL backend (MUJOCO_GL) when it is imported, while the test run has MUJOCO_GL=disable."""

import ctypes.util
import glob
import os
import subprocess
import sys

import numpy as np
import pytest

import dr_tdmpc2 as dr

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Size I on reach (100-step episodes; evaluated on goals 0 and 5 of 6), tiny planner and batch, no online evaluation.
TINY = dict(
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
    online_eval_steps=0,
    eval_episodes=1,
    offline_adapt_steps=(0,),
    eval_env_ids=(0, 5),
    log_every=20,
    checkpoint_every=10_000,
    cuda=False,
    threads=1,
    evaluate_after_training=False,
)


def run_dr(args: dict, env: dict, setup: str = "") -> subprocess.CompletedProcess:
    code = f"{setup}\nimport dr_tdmpc2 as s\ns.main(s.Args(**{args!r}))"
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env={**os.environ, **env}, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result


def test_track_writes_an_offline_wandb_run_with_the_scalars_and_config(tmp_path):
    wandb_env = {f"WANDB_{key}": str(tmp_path / key.lower()) for key in ("DIR", "CACHE_DIR", "CONFIG_DIR", "DATA_DIR")}
    run_dr(
        {**TINY, "run_dir": str(tmp_path / "run"), "track": True, "wandb_project_name": "claw-test"},
        {**wandb_env, "WANDB_MODE": "offline", "WANDB_SILENT": "true"},
    )
    runs = glob.glob(str(tmp_path / "dir" / "wandb" / "offline-run-*"))
    assert len(runs) == 1, os.listdir(tmp_path / "dir")
    (records,) = glob.glob(os.path.join(runs[0], "run-*.wandb"))  # what `wandb sync` would upload
    data = open(records, "rb").read()
    assert b"claw-test" in data and b"wandb_project_name" in data and b"offline_adapt_steps" in data  # run and config
    assert b"losses/wm_loss" in data and b"charts/SPS" in data  # the TensorBoard scalars, mirrored


def test_capture_video_without_a_gl_backend_says_so_in_one_line(tmp_path, capsys):
    if os.environ.get("MUJOCO_GL") != "disable":
        pytest.skip("needs MUJOCO_GL=disable (the test command's)")
    dr.main(dr.Args(**{**TINY, "run_dir": str(tmp_path / "run"), "capture_video": True}))
    lines = [line for line in capsys.readouterr().out.splitlines() if "--capture-video" in line]
    assert len(lines) == 1 and "MUJOCO_GL=disable" in lines[0] and "osmesa" in lines[0], lines
    assert not os.path.exists(tmp_path / "run" / "videos")


def test_capture_video_records_the_first_offline_episode_of_every_environment(tmp_path):
    if ctypes.util.find_library("OSMesa") is None:
        pytest.skip("no OSMesa (Debian: apt-get install libosmesa6; .ci/run installs it)")
    # 64 x 48 frames keep software rendering (OSMesa) cheap; the scripts record 320 x 240
    result = run_dr(
        {**TINY, "run_dir": str(tmp_path / "run"), "capture_video": True, "evaluate_after_training": True},
        {"MUJOCO_GL": "osmesa"},
        setup="import common.envs\ncommon.envs.RENDER_SIZE = (48, 64)",
    )
    if "warning: --capture-video records nothing" in result.stdout:
        pytest.fail("no OSMesa here (Debian: apt-get install libosmesa6): " + result.stdout.splitlines()[-1])
    videos = sorted(os.listdir(tmp_path / "run" / "videos"))
    assert videos == [f"env{env_id}_offline_0steps.mp4" for env_id in (0, 5)]
    import imageio.v2 as imageio

    frames = np.stack(imageio.mimread(str(tmp_path / "run" / "videos" / videos[0]), memtest=False))
    assert frames.shape == (101, 48, 64, 3)  # the reset frame and one per agent step
    assert len(np.unique(frames.reshape(-1, 3), axis=0)) > 10  # a scene, not one colour
