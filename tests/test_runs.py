"""Runs a user can trust (every script alike): arguments checked before any work, checked checkpoints,
--resume with the saved arguments, progress and start-up lines, duplicated TensorBoard steps reported."""

import io
import json
import os
import re
import time

import pytest
import torch
import tyro

import claw_tdmpc2 as claw
import common.evaluation as common_evaluation
import concat_tdmpc2 as concat
import dr_tdmpc2 as dr
import film_tdmpc2 as film
import oracle_tdmpc2 as oracle
import posthoc_tdmpc2 as posthoc
import st_tdmpc2 as st
from experiments import aggregate, archive, sweep

SCRIPTS = [claw, dr, st, oracle, film, concat, posthoc]


def args_for(script, tmp_path, **overrides):
    base = dict(family="cheetah_walker" if script is posthoc else "reach", cuda=False, run_dir=str(tmp_path / "run"))
    return script.Args(**{**base, **overrides})


def fake_checkpoint(path, script, method=None, **args):
    """The parts of a checkpoint that are read before any work: method and arguments."""
    state = {
        "method": method or os.path.basename(script.__file__),
        "args": vars(args_for(script, path.parent, **args)),
        "model": {},
        "global_step": 0,
    }
    torch.save(state, path)
    return str(path)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda s: s.__name__)
def test_bad_counts_and_budgets_fail_before_any_work(script, tmp_path):
    cases = [
        (dict(total_timesteps=0), "--total-timesteps must be a positive integer, got 0"),
        (dict(total_timesteps=-5), "--total-timesteps must be a positive integer, got -5"),
        (dict(batch_size=0), "--batch-size must be a positive integer, got 0"),
        (dict(log_every=0), "--log-every must be a positive integer, got 0"),
        (dict(checkpoint_every=0), "--checkpoint-every must be a positive integer"),
        (dict(eval_episodes=0), "--eval-episodes must be a positive integer"),
        (dict(num_samples=0, num_elites=0, num_pi_trajs=0), "--num-elites"),
        (dict(context_episodes=0), "--context-episodes"),
        (dict(burst_updates=-1), "--burst-updates must be >= 0, got -1"),
        (dict(online_eval_steps=-1), "--online-eval-steps must be >= 0"),
        (dict(eval_only=True, resume="x", checkpoint="x"), "does not exist|exclude each other"),
    ]
    if script is posthoc:  # a pass is half the budget; each has its own 3-episode prefill of one environment
        cases.append(
            (
                dict(total_timesteps=3000),
                r"half of --total-timesteps \(one pass\): 1500 must exceed the random-action prefill of 1500 steps",
            )
        )
    elif script is st:  # one environment: 5 walker episodes
        cases.append(
            (
                dict(family="walker", total_timesteps=2500),
                r"--total-timesteps: 2500 must exceed the random-action prefill of 2500 steps",
            )
        )
    else:  # one 500-step episode of each of walker's 20 environments
        cases.append(
            (
                dict(family="walker", total_timesteps=5000),
                r"--total-timesteps: 5000 must exceed the random-action prefill of 10000 steps",
            )
        )
    if script is not posthoc:  # post-hoc evaluates cheetah only: it has no --eval-env-ids
        for ids in ((6,), (-1,), (0, 0)):
            cases.append((dict(eval_env_ids=ids), r"--eval-env-ids must be distinct ids in 0\.\.5 \(reach\), got \["))
    for overrides, message in cases:
        with pytest.raises(SystemExit, match=message):
            script.main(args_for(script, tmp_path, **overrides))
    assert not os.path.exists(tmp_path / "run")


def test_help_lists_the_families(capsys):
    with pytest.raises(SystemExit):
        tyro.cli(claw.Args, args=["--help"])
    assert "walker,reach,push,go1,cheetah_walker" in capsys.readouterr().out.replace(" ", "").replace("\n", "")


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda s: s.__name__)
def test_saved_replay_holds_the_transitions_not_the_capacity(script):
    """A checkpoint's replay buffer grows with the transitions stored, not with the preallocated capacity (a saved
    slice would carry its whole storage), and loads back the same."""
    replay = script.ReplayBuffer(20_000, 8, 2, 1, 3, torch.device("cpu"))
    for t in range(10):
        replay.add(0, torch.full((8,), float(t)), torch.ones(2), float(t), torch.full((8,), t + 1.0), first=t == 0)
    saved = io.BytesIO()
    torch.save(replay.state_dict(), saved)
    assert len(saved.getvalue()) < 20_000  # the capacity alone is 20,000 x 19 floats = 1.5 MB
    saved.seek(0)
    loaded = script.ReplayBuffer(20_000, 8, 2, 1, 3, torch.device("cpu"))
    loaded.load_state_dict(torch.load(saved))
    assert (
        loaded.size == 10
        and torch.equal(loaded.obs[:10], replay.obs[:10])
        and torch.equal(loaded.reward[:10], replay.reward[:10])
    )


@pytest.mark.parametrize("script", [dr, st, posthoc], ids=lambda s: s.__name__)
def test_another_scripts_checkpoint_is_refused(script, tmp_path):
    path = fake_checkpoint(tmp_path / "claw.pt", claw)
    for args in (args_for(script, tmp_path, eval_only=True, checkpoint=path), args_for(script, tmp_path, resume=path)):
        with pytest.raises(
            SystemExit, match=f"claw.pt is a claw_tdmpc2.py checkpoint, expected one written by {script.__name__}.py"
        ):
            script.main(args)
    # a checkpoint from before the method was recorded is told apart by its run's exp_name
    state = torch.load(path, weights_only=False)
    del state["method"]
    torch.save(state, path)
    with pytest.raises(SystemExit, match="is a claw_tdmpc2.py checkpoint"):
        script.main(args_for(script, tmp_path, eval_only=True, checkpoint=path))


def test_unreadable_checkpoints_give_one_line(tmp_path):
    real = fake_checkpoint(tmp_path / "real.pt", claw)
    data = open(real, "rb").read()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.pt").write_text("not a checkpoint")
    torch.save([1, 2, 3], tmp_path / "list.pt")
    for name, message in (
        ("truncated", r"cannot read checkpoint .*truncated.pt \(truncated, corrupt"),
        ("text", r"cannot read checkpoint .*text.pt \(truncated"),
        ("list", "list.pt is not a checkpoint of these scripts"),
    ):
        with pytest.raises(SystemExit, match=message) as error:
            claw.main(args_for(claw, tmp_path, resume=str(tmp_path / f"{name}.pt")))
        assert "\n" not in str(error.value)


def test_checkpoint_of_another_configuration_is_refused(tmp_path):
    args = dr.Args(family="reach", model_size="I")
    model = dr.WorldModel(39, 4, "I", args)
    path = str(tmp_path / "checkpoint.pt")
    dr.save_checkpoint(path, 0, 0, model, dr.make_optimizers(model, args), dr.RunningScale(args.tau, "cpu"), None, args)
    dr.load_checkpoint(path, dr.WorldModel(39, 4, "I", args))  # the same configuration loads
    with pytest.raises(SystemExit, match="holds model_size I, expected G"):
        dr.load_checkpoint(path, dr.WorldModel(39, 4, "G", dr.Args(family="reach", model_size="G")))
    with pytest.raises(SystemExit, match=r"holds dims \(39, 4\), expected \(24, 6\)"):
        dr.load_checkpoint(path, dr.WorldModel(24, 6, "I", args))
    state = torch.load(path, weights_only=False)
    state["args"]["model_size"] = "G"  # weights that do not match what the checkpoint claims
    torch.save(state, path)
    with pytest.raises(SystemExit, match="does not fit this configuration: size mismatch for") as error:
        dr.load_checkpoint(path, dr.WorldModel(39, 4, "G", dr.Args(family="reach", model_size="G")))
    assert "\n" not in str(error.value)


def test_resume_and_eval_only_refuse_conflicting_flags(tmp_path):
    path = fake_checkpoint(tmp_path / "checkpoint.pt", claw, model_size="I", rank=2, batch_size=16, total_timesteps=640)
    with pytest.raises(SystemExit, match="--batch-size 32 conflicts with 16 in .*checkpoint.pt"):
        claw.main(claw.Args(resume=path, batch_size=32, cuda=False))
    with pytest.raises(SystemExit, match="--total-timesteps 2000 conflicts with 640"):
        claw.main(claw.Args(resume=path, total_timesteps=2000, cuda=False))
    with pytest.raises(SystemExit, match="--model-size F conflicts with I"):
        claw.main(claw.Args(eval_only=True, checkpoint=path, model_size="F", cuda=False))


def test_start_up_and_progress_lines():
    now = time.time()
    line = claw.progress_text(50, 150, 0, now - 10, now - 20, [(1.0, 1.0), (3.0, 0.0)], "reach")
    assert re.fullmatch(r"return 2\.0 \| success 0\.50 \| SPS [45] \| elapsed 0:00:(19|20) \| ETA 0:00:(19|20)", line), line
    # no success off Meta-World
    assert claw.progress_text(10, 20, 0, now - 1, now - 1, [], "walker").startswith("return - | SPS")
    if not torch.cuda.is_available():
        text = claw.describe_device(claw.Args(model_size="A"), torch.device("cpu"))
        assert (
            "device: cpu" in text
            and "warning: --cuda was asked for but CUDA is not available" in text
            and "--model-size F" in text
        )
    table = claw.hyperparameter_text(claw.Args(), total_timesteps=50_000, seed_steps=1000, discount=0.99, device="cpu")
    assert "|total_timesteps|50000|" in table and "|seed_steps|1000|" in table and "|device|cpu|" in table
    assert "|git_commit|" in table and "|git_commit||" not in table


def test_aggregate_reports_duplicated_steps(tmp_path, capsys):
    from torch.utils.tensorboard import SummaryWriter

    run_dir = tmp_path / "claw__reach__I__r2__s1"
    for value in (10.0, 30.0):  # two processes logging the same steps, as a resume without purge_step did
        writer = SummaryWriter(str(run_dir))
        writer.add_scalar("eval/online/episodic_return", value, 100)
        writer.add_scalar("eval/offline/episodic_return", value, 0)
        writer.close()
        # TensorBoard orders event files by name, whose last field is a per-process counter (9 sorts after 10): a new
        # second in the name's time field keeps the two files in the order they were written
        time.sleep(1.1)
    (run_dir / "run.json").write_text(
        json.dumps({"method": "claw", "family": "reach", "size": "I", "rank": 2, "seed": 1, "status": "done"})
    )
    aggregate.main([str(tmp_path)])
    out = capsys.readouterr().out
    assert f"warning: {run_dir} has duplicated steps in 2 tag(s)" in out
    assert (
        "Runs with duplicated TensorBoard steps" in out and "claw__reach__I__r2__s1" in (tmp_path / "summary.md").read_text()
    )
    assert aggregate.load_runs(str(tmp_path))[0]["scalars"]["eval/online/episodic_return"] == [(100, 30.0)]  # the last value


def test_launcher_arguments(tmp_path):
    for workers in ("0", "-2"):
        with pytest.raises(SystemExit, match=f"--workers must be >= 1, got {workers}"):
            sweep.main(["exp1", "--scale", "smoke", "--dry-run", "--workers", workers])
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit, match="exists and is not a directory"):
        sweep.main(["exp1", "--scale", "smoke", "--dry-run", "--root", str(tmp_path / "file")])


def kill_at_update(monkeypatch, script, call: int):
    """Make script.update raise KeyboardInterrupt on its call-th call: a kill in the middle of the burst."""
    update, calls = script.update, [0]

    def killed(*a, **k):
        calls[0] += 1
        if calls[0] == call:
            raise KeyboardInterrupt
        return update(*a, **k)

    monkeypatch.setattr(script, "update", killed)


def test_a_run_killed_in_its_burst_resumes_from_its_prefill(tmp_path, capsys, monkeypatch):
    from test_claw import tiny_args

    args = tiny_args(tmp_path, total_timesteps=620)
    kill_at_update(monkeypatch, claw, 3)
    with pytest.raises(KeyboardInterrupt):
        claw.main(args)
    monkeypatch.undo()
    checkpoint = os.path.join(args.run_dir, "checkpoint.pt")
    state = torch.load(checkpoint, weights_only=False)
    assert (state["global_step"], state["burst_left"], state["replay"]["size"], state["method"]) == (
        600,
        5,
        600,
        "claw_tdmpc2.py",
    )
    capsys.readouterr()
    claw.main(claw.Args(resume=checkpoint))  # no new context pool or prefill: the burst again, then training
    out = capsys.readouterr().out
    assert "at step 600" in out and "prefilled 600 steps; 5 burst updates" in out and "step 620/620" in out
    state = torch.load(checkpoint, weights_only=False)
    assert (state["global_step"], state["burst_left"], state["replay"]["size"]) == (620, 0, 620)


def test_posthoc_killed_in_its_first_burst_redoes_it_and_goes_on(tmp_path, capsys, monkeypatch):
    from test_baselines_incontext import tiny_args

    args = tiny_args(posthoc, tmp_path)
    kill_at_update(monkeypatch, posthoc, 3)
    with pytest.raises(KeyboardInterrupt):
        posthoc.main(args)
    monkeypatch.undo()
    checkpoint = os.path.join(args.run_dir, "checkpoint.pt")
    state = torch.load(checkpoint, weights_only=False)
    assert (state["global_step"], state["pass"], state["burst_left"]) == (500, 1, 5)
    capsys.readouterr()
    posthoc.main(posthoc.Args(resume=checkpoint))
    out = capsys.readouterr().out
    assert "at step 500 in pass 1" in out and "pass 1: prefilled up to step 500; 5 burst updates" in out
    assert "pass 2: prefilled up to step 1050; 5 burst updates" in out and "step 1100/1100" in out
    state = torch.load(checkpoint, weights_only=False)
    assert (state["global_step"], state["pass"], state["burst_left"]) == (1100, 2, 0)


def eval_lines(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith("eval")]


def raise_on_call(function, n: int):
    """`function`, killed (KeyboardInterrupt, as a kill -9 would stop it) on its n-th call."""
    calls = [0]

    def killed(*a, **k):
        calls[0] += 1
        if calls[0] == n:
            raise KeyboardInterrupt
        return function(*a, **k)

    return killed


def raise_at_step(progress_text, step: int):
    def killed(s, *rest):
        if s == step:
            raise KeyboardInterrupt
        return progress_text(s, *rest)

    return killed


# script, its tiny arguments, and kill points, in the order one run meets them: (patched name, wrapper,
# the step of the last checkpoint before the kill)
EXACT = {
    "claw": (
        claw,
        dict(family="reach", rank=2, total_timesteps=800, checkpoint_every=100, eval_env_ids=(0, 1)),
        [
            ("update", lambda f: raise_on_call(f, 3), 600),  # in the burst: the checkpoint after the prefill
            ("progress_text", lambda f: raise_at_step(f, 620), 600),  # after the burst, before an episode ends
            ("progress_text", lambda f: raise_at_step(f, 760), 700),  # after a periodic checkpoint at an episode end
            ("online_adaptation", lambda f: raise_on_call(f, 2), 800),  # in the final evaluation, goal 1
        ],
    ),
    "dr": (
        dr,
        dict(
            family="reach", rank=2, total_timesteps=800, checkpoint_every=100, offline_adapt_steps=(0, 2), eval_env_ids=(0, 1)
        ),
        [
            ("progress_text", lambda f: raise_at_step(f, 760), 700),
            ("offline_adaptation", lambda f: raise_on_call(f, 1), 800),  # in goal 0's evaluation: nothing to keep
            ("offline_adaptation", lambda f: raise_on_call(f, 4), 800),  # in goal 1's second sweep point
        ],
    ),
    "posthoc": (
        posthoc,
        dict(family="cheetah_walker", rank=2, total_timesteps=1100, log_every=25, checkpoint_every=550),
        [
            ("collect_episodes", lambda f: raise_on_call(f, 1), 550),  # pass 2 begins: pass 1's end is an episode end
            ("progress_text", lambda f: raise_at_step(f, 1075), 1050),  # in pass 2: the checkpoint after its burst
        ],
    ),
}


@pytest.mark.parametrize("name", list(EXACT))
def test_killed_and_resumed_runs_equal_uninterrupted_ones(name, tmp_path, capsys, monkeypatch):
    """Exact resume on the CPU: a run killed again and again, each time continued by --resume alone, ends with
    the weights and evaluation of an uninterrupted run with the same seed."""
    from test_baselines_incontext import TINY

    script, overrides, kills = EXACT[name]
    base = {k: v for k, v in TINY.items() if k in script.Args.__dataclass_fields__}  # dr: no context pool
    cheap = dict(num_samples=16, num_elites=4, num_pi_trajs=2, iterations=1, evaluate_after_training=True)
    args = script.Args(**{**base, **overrides, **cheap, "run_dir": str(tmp_path / "whole")})
    script.main(args)
    whole_out = capsys.readouterr().out
    whole = torch.load(os.path.join(args.run_dir, "checkpoint.pt"), weights_only=False)
    assert len(eval_lines(whole_out)) >= 2
    checkpoint = str(tmp_path / "killed" / "checkpoint.pt")
    for i, (attr, wrap, saved_step) in enumerate(kills):
        owner = common_evaluation if attr.endswith("_adaptation") else script  # the protocols live in common/
        monkeypatch.setattr(owner, attr, wrap(getattr(owner, attr)))
        with pytest.raises(KeyboardInterrupt):
            script.main(
                script.Args(resume=checkpoint) if i else script.Args(**{**vars(args), "run_dir": os.path.dirname(checkpoint)})
            )
        monkeypatch.undo()
        assert torch.load(checkpoint, weights_only=False)["global_step"] == saved_step, attr
    # resumed from the launcher's carried copy (--carry), which drops replay and context pool once training is over
    carried = os.path.join(archive.carry_run(os.path.dirname(checkpoint), str(tmp_path / "carry")), "checkpoint.pt")
    killed_in_evaluation = kills[-1][2] == overrides["total_timesteps"]
    assert (torch.load(carried, weights_only=False)["replay"] is None) == killed_in_evaluation
    capsys.readouterr()
    script.main(script.Args(resume=carried))
    out = capsys.readouterr().out
    assert f"at step {kills[-1][2]}" in out
    resumed = torch.load(carried, weights_only=False)
    for part in ("model", "hypernet"):
        for key, value in whole.get(part, {}).items():
            assert torch.equal(value, resumed[part][key]), (part, key)
    # an evaluation killed after some environments takes them from its progress file; the rest and the
    # family results equal the uninterrupted run's
    finished = {"claw": 1, "dr": 1, "posthoc": 0}[name]
    assert (
        f"resumed the evaluation from {tmp_path / 'carry' / 'killed' / 'evaluation_progress.pt'}: {finished} environments done"
        in out
    ) == (finished > 0)
    assert eval_lines(out) == [
        line for line in eval_lines(whole_out) if not any(line.startswith(f"eval env {e}:") for e in range(finished))
    ]
    assert not os.path.exists(tmp_path / "carry" / "killed" / "evaluation_progress.pt")


def test_evaluation_progress_is_taken_up_only_for_the_weights_it_was_saved_with(tmp_path, capsys):
    from common.evaluation import load_evaluation_progress, save_evaluation_progress, weights_digest

    model, path = torch.nn.Linear(3, 2), str(tmp_path / "evaluation_progress.pt")
    results = {"online": {0: [{"step": 100, "return": 1.0, "success": 0.0}]}, "offline": {0: {0: []}}}
    torch.manual_seed(7)
    save_evaluation_progress(path, results, weights_digest(model))
    expected_draw = torch.rand(3)
    torch.manual_seed(8)
    assert load_evaluation_progress(path, weights_digest(model)) == results
    assert torch.equal(torch.rand(3), expected_draw)  # the generators continue where the evaluation stopped
    with torch.no_grad():
        model.weight[0, 0] += 1e-6
    assert load_evaluation_progress(path, weights_digest(model)) == {"online": {}, "offline": {}}
    assert "saved by an evaluation of other weights" in capsys.readouterr().out
