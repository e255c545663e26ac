"""Bad values and faults (every script alike): flags checked against their ranges before any work, a diverging run
stopped with the last finite checkpoint kept, no run directory reused without a word, SIGINT saving at the next exact
resume point, a full disk during a save, and the --resume / --checkpoint / --eval-only flag contract."""

import os
import signal
import subprocess
import sys

import pytest
import torch

import claw_tdmpc2 as claw
import concat_tdmpc2 as concat
import dr_tdmpc2 as dr
import film_tdmpc2 as film
import oracle_tdmpc2 as oracle
import posthoc_tdmpc2 as posthoc
import st_tdmpc2 as st

SCRIPTS = [claw, dr, st, oracle, film, concat, posthoc]
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# a run of a few seconds: size I, a 600-step prefill (one 100-step episode per Reach goal), a tiny planner
TINY = [
    "--family",
    "reach",
    "--model-size",
    "I",
    "--rank",
    "2",
    "--no-cuda",
    "--threads",
    "1",
    "--compile",
    "off",
    "--seed-steps",
    "100",
    "--burst-updates",
    "2",
    "--batch-size",
    "16",
    "--num-samples",
    "16",
    "--num-elites",
    "4",
    "--num-pi-trajs",
    "2",
    "--iterations",
    "1",
    "--log-every",
    "50",
    "--no-evaluate-after-training",
]


def args_for(script, tmp_path, **overrides):
    base = dict(family="cheetah_walker" if script is posthoc else "reach", cuda=False, run_dir=str(tmp_path / "run"))
    return script.Args(**{**base, **overrides})


BAD = [
    (dict(learning_rate=-1e-3), "--learning-rate must be > 0, got -0.001"),
    (dict(learning_rate=float("inf")), "--learning-rate must be finite, got inf"),
    (dict(grad_clip_norm=-1.0), "--grad-clip-norm must be > 0, got -1.0"),
    (dict(discount=1.5), "--discount must be in (0, 1], got 1.5"),
    (dict(tau=0.0), "--tau must be in (0, 1], got 0.0"),
    (dict(rho=float("nan")), "--rho must be finite, got nan"),
    (dict(temperature=0.0), "--temperature must be > 0, got 0.0"),
    (dict(min_std=3.0), "need --min-std <= --max-std, got 3.0 > 2.0"),
    (dict(min_std=0.0), "--min-std must be > 0, got 0.0"),
    (dict(vmin=5.0, vmax=1.0), "--vmin < --vmax"),
    (dict(seed=-1), "--seed must be an integer in 0.."),
    (dict(seed=2**32), "--seed must be an integer in 0.."),
    (dict(consistency_coef=-1.0), "--consistency-coef must be >= 0, got -1.0"),
    (dict(horizon=100), "--horizon must be in 1..99"),
]


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda s: s.__name__)
def test_out_of_range_flags_are_refused_before_any_work(script, tmp_path):
    cases = BAD + (
        [(dict(model_size="I", rank=9), "--rank must be in 1..8")] if "rank" in script.Args.__dataclass_fields__ else []
    )
    if script is posthoc:  # cheetah_walker's episodes are 500 steps
        cases = [(o, m) if "horizon" not in o else (dict(horizon=500), "--horizon must be in 1..499") for o, m in cases]
    for overrides, message in cases:
        with pytest.raises(
            SystemExit, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.").replace("+", r"\+")
        ):
            script.main(args_for(script, tmp_path, **overrides))
        assert not os.path.exists(tmp_path / "run"), overrides  # nothing written
    with pytest.raises(SystemExit, match="--checkpoint is read by --eval-only only"):
        script.main(args_for(script, tmp_path, checkpoint=__file__))


def test_a_diverging_run_stops_with_the_step_and_the_last_finite_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    args = claw.Args(**{**tiny_args(claw), "learning_rate": 1e30, "hypernet_lr": 1e30, "run_dir": str(run_dir)})
    with pytest.raises(SystemExit, match=r"error: the run diverged (at|before) step \d+: .* lower --learning-rate") as stopped:
        claw.main(args)
    assert "\n" not in str(stopped.value)
    state = torch.load(run_dir / "checkpoint.pt", weights_only=False)  # the checkpoint after the prefill
    assert all(torch.isfinite(t).all() for t in state["model"].values() if t.is_floating_point())


def tiny_args(script) -> dict:
    return dict(
        family="reach",
        model_size="I",
        rank=2,
        cuda=False,
        compile="off",
        seed_steps=100,
        burst_updates=2,
        batch_size=16,
        num_samples=16,
        num_elites=4,
        num_pi_trajs=2,
        iterations=1,
        total_timesteps=700,
        context_pool_episodes=2,
        context_episodes=1,
        evaluate_after_training=False,
        log_every=50,
    )


def test_a_run_directory_holding_a_run_is_refused_and_overwrite_starts_over(tmp_path, capsys):
    run_dir = tmp_path / "run"
    args = dict(tiny_args(dr), run_dir=str(run_dir))
    args.pop("context_pool_episodes")
    dr.main(dr.Args(**args))
    first = os.path.getmtime(run_dir / "checkpoint.pt")
    with pytest.raises(
        SystemExit,
        match=f"--run-dir {run_dir} already holds a run .checkpoint.pt.; continue it with --resume "
        f"{run_dir / 'checkpoint.pt'}, or start over with --overwrite",
    ):
        dr.main(dr.Args(**args))
    assert os.path.getmtime(run_dir / "checkpoint.pt") == first
    dr.main(dr.Args(**args, overwrite=True))
    assert len([n for n in os.listdir(run_dir) if n.startswith("events.out")]) == 1  # the old run's events are gone


def test_a_full_disk_during_a_save_gives_one_line_and_keeps_the_previous_file(tmp_path, monkeypatch):
    path = str(tmp_path / "checkpoint.pt")
    claw.atomic_save({"global_step": 1}, path)

    def full_disk(state, target):
        with open(target, "wb") as f:
            f.write(b"partial")
        raise RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos 128 vs 64")

    monkeypatch.setattr(claw.torch, "save", full_disk)
    with pytest.raises(
        SystemExit, match=r"error: cannot write .*checkpoint.pt \(\[enforce fail.*MiB free\); the previous one is intact"
    ):
        claw.atomic_save({"global_step": 2}, path)
    monkeypatch.undo()
    assert not os.path.exists(path + ".tmp")
    assert torch.load(path, weights_only=False) == {"global_step": 1}


def test_flags_typed_on_the_command_line_are_checked_even_at_their_default():
    assert claw.typed_flags(["--num-samples", "512", "--no-cuda", "--rank=4", "--family", "reach"]) == {
        "num_samples",
        "cuda",
        "rank",
        "family",
    }
    saved = vars(claw.Args(num_samples=64, online_eval_steps=20))
    with pytest.raises(SystemExit, match="--num-samples 512 conflicts with 64"):  # typed: 512 is the default, yet given
        claw.adopt_args(claw.Args(), saved, None, "ckpt", typed={"num_samples"})
    args = claw.Args()
    claw.adopt_args(args, saved, None, "ckpt", typed=set())  # nothing typed: the checkpoint's values
    assert args.num_samples == 64
    # --eval-only: the run's own evaluation settings unless given anew
    args = claw.Args(online_eval_steps=50)
    claw.adopt_args(
        args, saved, claw.EVALUATION_FLAGS, "ckpt", typed={"online_eval_steps"}, free=claw.RESUME_FREE + claw.EVALUATION_FLAGS
    )
    assert (args.online_eval_steps, args.num_samples) == (50, 64)
    assert "Exp 1 50 online agent steps" in claw.describe_evaluation(args)


def test_sigint_saves_at_the_next_episode_end_and_resume_ends_like_an_uninterrupted_run(tmp_path):
    """A real SIGINT to a running script: it saves at the next episode end, prints the command that resumes it and
    exits 130; --resume then ends with the weights of a run that was never interrupted."""
    script = [sys.executable, os.path.join(REPO, "dr_tdmpc2.py"), *TINY, "--total-timesteps", "800"]
    env = {**os.environ, "MUJOCO_GL": "disable", "OMP_NUM_THREADS": "1"}
    subprocess.run(script + ["--run-dir", str(tmp_path / "whole")], env=env, check=True, capture_output=True)
    run = subprocess.Popen(
        script + ["--run-dir", str(tmp_path / "cut")], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines = []
    for line in run.stdout:
        lines.append(line)
        if line.startswith("step 650/"):
            run.send_signal(signal.SIGINT)
    assert run.wait() == 128 + signal.SIGINT, "".join(lines)
    text = "".join(lines)
    assert "SIGINT: stopped at step 700; resume with: python dr_tdmpc2.py --resume" in text
    assert "Traceback" not in text
    assert torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)["global_step"] == 700
    subprocess.run(
        [sys.executable, os.path.join(REPO, "dr_tdmpc2.py"), "--resume", str(tmp_path / "cut" / "checkpoint.pt")],
        env=env,
        check=True,
        capture_output=True,
    )
    whole = torch.load(tmp_path / "whole" / "checkpoint.pt", weights_only=False)["model"]
    resumed = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)["model"]
    assert all(torch.equal(whole[k], resumed[k]) for k in whole)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda s: s.__name__)
def test_the_model_size_defaults_to_the_papers_on_cuda_and_f_on_a_cpu(script, monkeypatch):
    monkeypatch.setattr(script.torch.cuda, "is_available", lambda: True)
    assert script.default_model_size(script.Args()) == "A"
    assert script.default_model_size(script.Args(cuda=False)) == "F"
    monkeypatch.setattr(script.torch.cuda, "is_available", lambda: False)
    assert script.Args().model_size is None and script.default_model_size(script.Args()) == "F"


def test_a_run_says_its_size_its_evaluation_and_then_an_estimate_of_its_duration():
    """Without --model-size a CPU run says size F in its first line; the evaluation line names the flags that shorten
    it; after 30 training steps an estimate of training and evaluation time follows, once."""
    command = [sys.executable, os.path.join(REPO, "claw_tdmpc2.py"), *TINY, "--total-timesteps", "700", "--dry-run"]
    command.remove("--model-size"), command.remove("I"), command.remove("--rank"), command.remove("2")
    env = {**os.environ, "MUJOCO_GL": "disable", "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    out = subprocess.run(command, env=env, check=True, capture_output=True, text=True).stdout
    assert out.splitlines()[0] == "model size F: the default on a CPU (--model-size A is the paper's size)"
    clock = claw.RunClock(claw.Args(online_eval_steps=1000, eval_episodes=2), 10_000, 6, 100)
    printed = []
    clock.estimate = lambda step: printed.append(step) or "estimate"
    for _ in range(3):
        clock.lap("update")
    for step in range(1, 40):
        clock.lap("step", step)
    assert printed == [31] and len(clock.seconds["update"]) == 2 and len(clock.seconds["step"]) == 38
    clock.seconds = {"update": [0.0625], "step": [0.125]}
    text = claw.RunClock.estimate(clock, 1000)
    # training 9,000 x 125 ms; per environment Exp 1 1,000 x 125 ms, Exp 2 2 episodes x 100 x (125 - 62.5) ms; 6 environments
    assert text.startswith("estimate on this machine: training 0:18:45 more (125 ms per agent step), evaluation 0:13:45 (6")
    assert "Exp 1 0:02:05 and Exp 2 0:00:12 each; shorter: --online-eval-steps, --eval-episodes" in text
    assert "shorter: --online-eval-steps, --eval-episodes" in claw.describe_evaluation(claw.Args())
