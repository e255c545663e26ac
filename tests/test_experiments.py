"""Sweep tooling: CI math, recipes and launcher, aggregation, figures."""

import dataclasses
import json
import math
import os
import shlex
import shutil

import numpy as np
import pytest
import scipy.stats
import torch

from common.evaluation import mean_ci
from diagnostics import context_effect, context_identifiability, decoder_signal
from experiments import aggregate, figures, sweep


def test_mean_ci_matches_scipy_on_known_numbers():
    values = [547.8, 685.8, 721.5, 817.3, 814.2]
    mean, half = mean_ci(values)
    low, high = scipy.stats.t.interval(0.95, len(values) - 1, loc=np.mean(values), scale=scipy.stats.sem(values))
    assert mean == pytest.approx(717.32)
    assert (mean - half, mean + half) == pytest.approx((low, high))
    # hand check: sd of [1, 2, 3] is 1, t_{0.975, 2} = 4.302653
    assert mean_ci([1.0, 2.0, 3.0])[1] == pytest.approx(4.302653 / np.sqrt(3), rel=1e-6)
    assert np.isnan(mean_ci([5.0])[1])


def test_paper_recipes_follow_the_tables():
    exp12 = sweep.plan_runs(["exp1", "exp2"], "paper")
    assert len(exp12) == 4 * 4 * 5  # families x methods x seeds, shared by both experiments
    assert all(r.experiments == ["exp1", "exp2"] and r.size == "A" and r.rank == 16 for r in exp12)
    assert [r.seed for r in exp12[:16]] == [1] * 16  # seed-major: all families and methods at seed 1 first
    exp3 = sweep.recipe("exp3", "paper")
    assert {(r.size, r.rank) for r in exp3 if r.method == "claw"} == set(sweep.SIZE_RANKS.items())
    # Exp 3's size-F CLAW runs are Exp 4's rank-8 and Exp 5's CLAW runs: planned once
    shared = sweep.plan_runs(["exp3", "exp4", "exp5"], "paper")
    claw_f8 = [r for r in shared if r.method == "claw" and r.size == "F" and r.rank == 8]
    assert len(claw_f8) == 5 and all(r.experiments == ["exp3", "exp4", "exp5"] for r in claw_f8)
    assert "--offline-adapt-steps" not in sweep.recipe("exp1", "cpu")[0].command("x")  # CLAW has no sweep


def test_launcher_dry_run_lists_commands_and_skips_finished(tmp_path, capsys):
    runs = sweep.plan_runs(["exp1"], "smoke")
    done_dir = tmp_path / runs[0].name
    sweep.write_status(str(done_dir), runs[0], runs[0].command(str(done_dir)), "done")
    interrupted = tmp_path / runs[1].name
    interrupted.mkdir()
    (interrupted / "checkpoint.pt").write_bytes(b"")
    assert sweep.launch(runs, str(tmp_path), workers=2, dry_run=True) == 0
    out = capsys.readouterr().out
    assert f"skip (done)  {runs[0].name}" in out
    assert f"--resume {interrupted / 'checkpoint.pt'}" in out
    assert out.count("claw_tdmpc2.py") == len([r for r in runs if r.method == "claw"]) - 1
    with pytest.raises(SystemExit, match="unknown experiment"):
        sweep.recipe("exp9", "paper")


def test_restarted_launcher_skips_live_runs_resumes_dead_ones_and_reports_changed_recipes(tmp_path, capsys, monkeypatch):
    live, dead, done, queued = sweep.plan_runs(["exp1"], "smoke")[:4]
    for run in (live, dead):
        sweep.write_status(str(tmp_path / run.name), run, run.command(str(tmp_path / run.name)), "running")
    held = sweep.lock_run(str(tmp_path / live.name))  # a live process (the first launcher's) owns it
    (tmp_path / dead.name / "run.lock").touch()  # its process died: the lock file stays, the lock does not
    (tmp_path / dead.name / "checkpoint.pt").write_bytes(b"")
    changed = done.command(str(tmp_path / done.name))
    changed[changed.index("--total-timesteps") + 1] = "999"
    sweep.write_status(str(tmp_path / done.name), done, changed, "done")
    # submitted by an earlier launcher, still pending in SLURM
    sweep.write_status(
        str(tmp_path / queued.name), queued, queued.command(str(tmp_path / queued.name)), "queued", slurm_job="12_3"
    )
    monkeypatch.setattr(sweep, "slurm_queued", lambda job_id: job_id == "12_3")
    try:
        pending = sweep.pending_runs([live, dead, done, queued], str(tmp_path))
        assert [run for run, _ in pending] == [dead]
        out = capsys.readouterr().out
        assert f"skip (running) {live.name}" in out and f"skip (done)  {done.name}" in out
        assert f"skip (queued 12_3) {queued.name}" in out
        assert f"changed      {done.name}" in out and "--total-timesteps 999" in out
        assert f"resume {sweep.shlex.join(dead.command(str(tmp_path / dead.name)))} --resume " in out
        # the run itself checks the lock too (a second launcher's job racing the first): no process starts
        assert sweep.RunJob()(live, str(tmp_path / live.name), {}) == "busy"
        assert not (tmp_path / live.name / "stdout.log").exists()
        assert sweep.run_is_live(str(tmp_path / live.name)) and not sweep.run_is_live(str(tmp_path / dead.name))
        problems = dict(aggregate.summarize(aggregate.load_runs(str(tmp_path)))[2])
        assert problems[str(tmp_path / live.name)].startswith("still running")
        assert "it died" in problems[str(tmp_path / dead.name)]
        # a second launcher shares the cores with the live run instead of taking them all (2 cores here)
        monkeypatch.setattr(sweep.os, "cpu_count", lambda: 2)
        capsys.readouterr()
        assert sweep.local_threads(str(tmp_path), workers=1) == "1"
        assert f"1 run(s) of another launcher live in {tmp_path} ({live.name})" in capsys.readouterr().out
    finally:
        os.close(held)
    assert not sweep.run_is_live(str(tmp_path / live.name))
    assert sweep.local_threads(str(tmp_path), workers=1) == "2" and sweep.local_threads(str(tmp_path), workers=2) == "1"
    assert "another launcher" not in capsys.readouterr().out


def test_interrupted_runs_resume_before_new_runs_start(tmp_path):
    first, second, third = sweep.plan_runs(["exp1"], "smoke")[:3]
    (tmp_path / third.name).mkdir()
    (tmp_path / third.name / "checkpoint.pt").write_bytes(b"")  # cut by the previous launcher's stop
    pending = sweep.pending_runs([first, second, third], str(tmp_path))
    assert [run for run, _ in pending] == [third, first, second]


def test_run_job_resumes_a_dead_run_holding_its_lock(tmp_path, monkeypatch):
    run = sweep.plan_runs(["exp1"], "smoke")[0]
    run_dir = tmp_path / run.name
    run_dir.mkdir()
    (run_dir / "checkpoint.pt").write_bytes(b"")
    # stand-in script: prints its arguments and whether the run's lock is held while it runs
    probe = (
        "import fcntl, os, sys; fd = os.open(os.path.join(os.path.dirname(sys.argv[-1]), 'run.lock'), os.O_RDWR)\n"
        "try: fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB); print('lock free')\n"
        "except BlockingIOError: print('lock held')\nprint(sys.argv[1:])"
    )
    monkeypatch.setattr(sweep.Run, "command", lambda self, run_dir, cuda=False: [sweep.sys.executable, "-c", probe])
    assert sweep.RunJob()(run, str(run_dir), {"OMP_NUM_THREADS": "1"}) == "done"
    log = (run_dir / "stdout.log").read_text()
    assert "lock held" in log and f"'--resume', '{run_dir / 'checkpoint.pt'}'" in log
    record = sweep.read_status(str(run_dir))
    assert record["status"] == "done" and record["resumed"] and record["returncode"] == 0
    assert "--resume" not in record["command"]  # the recipe's command, compared on restarts
    # preemption: submitit requeues the same run, which then resumes from its checkpoint
    sweep.write_status(str(run_dir), run, ["x"], "running")
    delayed = sweep.RunJob().checkpoint(run, str(run_dir), {}, False, 120.0)
    assert isinstance(delayed.function, sweep.RunJob) and delayed.args == (run, str(run_dir), {}, False, 120.0)
    assert sweep.read_status(str(run_dir))["status"] == "requeued"
    # a script killed by SIGTERM (the machine shutting down) was interrupted, not failed: the next launcher resumes it
    monkeypatch.setattr(
        sweep.Run,
        "command",
        lambda self, run_dir, cuda=False: [
            sweep.sys.executable,
            "-c",
            "import os, signal; os.kill(os.getpid(), signal.SIGTERM)",
        ],
    )
    assert sweep.RunJob()(run, str(run_dir), {}) == "interrupted"
    assert sweep.read_status(str(run_dir))["returncode"] == -sweep.signal.SIGTERM


def test_slurm_launcher_submits_one_array_with_the_cli_resources(tmp_path, monkeypatch, capsys):
    submitted = {}

    class FakeExecutor:  # stands in for submitit.SlurmExecutor (CI runs the real one: experiments/slurm_ci.sh)
        def __init__(self, folder, max_num_timeout):
            submitted.update(folder=folder, max_num_timeout=max_num_timeout)

        def update_parameters(self, **parameters):
            submitted["parameters"] = parameters

        def map_array(self, fn, *columns):
            submitted["fn"], submitted["columns"] = fn, columns
            return [
                type("Job", (), {"job_id": f"7_{i}", "paths": type("P", (), {"stdout": f"log{i}"})})()
                for i in range(len(columns[0]))
            ]

    monkeypatch.setattr(sweep.submitit, "SlurmExecutor", FakeExecutor)
    monkeypatch.setattr(sweep.shutil, "which", lambda name: "/usr/bin/" + name)
    monkeypatch.setattr(sweep, "slurm_queued", lambda job_id: False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    sweep.main(
        [
            "exp1",
            "--scale",
            "smoke",
            "--methods",
            "claw",
            "--launcher",
            "slurm",
            "--root",
            str(tmp_path),
            "--partition",
            "gpu",
            "--time",
            "2:00:00",
            "--cpus-per-task",
            "4",
            "--gpus-per-task",
            "1",
            "--workers",
            "8",
            "--sbatch",
            "qos=high",
            "--sbatch",
            "mem-per-cpu=2G",
        ]
    )
    parameters = submitted["parameters"]
    assert (parameters["partition"], parameters["time"], parameters["cpus_per_task"], parameters["gpus_per_task"]) == (
        "gpu",
        120,
        4,
        1,
    )
    assert parameters["array_parallelism"] == 8 and parameters["additional_parameters"] == {"qos": "high", "mem_per_cpu": "2G"}
    assert isinstance(submitted["fn"], sweep.RunJob)
    runs, run_dirs, envs, cudas, _ = submitted["columns"]
    assert len(runs) == 2 and all(cudas) and envs[0]["OMP_NUM_THREADS"] == "4"  # threads follow --cpus-per-task
    assert [sweep.read_status(d)["slurm_job"] for d in run_dirs] == ["7_0", "7_1"]
    assert all(sweep.read_status(d)["status"] == "queued" for d in run_dirs)
    assert "submitted 2 runs as SLURM job array 7" in capsys.readouterr().out


def test_launcher_arguments_fail_in_one_line(capsys):
    for argv, message in (
        (["--partition", "gpu"], "--partition: options of --launcher slurm only"),
        (["--launcher", "slurm", "--dry-run", "--time", "soon"], "--time 'soon': expected"),
        (["--launcher", "slurm", "--dry-run", "--sbatch", "qos"], "--sbatch 'qos': expected KEY=VALUE"),
        (["--workers", "0"], "--workers must be >= 1, got 0"),
        (["--families", "reech", "--dry-run"], "--families reech: not in these recipes .they have go1 push reach walker."),
        (["--seeds", "0", "9", "--dry-run"], "--seeds 0 9: not in these recipes .they have 1 2 3 4 5."),
    ):
        with pytest.raises(SystemExit, match=message):
            sweep.main(["exp1", *argv])
    assert [sweep.parse_minutes(t) for t in ("90", "01:30:00", "1:00:01", "2-00:30")] == [90, 90, 61, 2910]
    sweep.main(["exp1", "--scale", "smoke", "--launcher", "slurm", "--dry-run", "--gpus-per-task", "1", "--root", "x"])
    assert "--no-cuda" not in capsys.readouterr().out  # GPU runs use CUDA


def test_family_and_seed_filters_pick_the_runs_a_launcher_starts(tmp_path, capsys):
    sweep.main(
        [
            "exp1",
            "decoder",
            "--scale",
            "learn",
            "--families",
            "reach",
            "--seeds",
            "2",
            "3",
            "--methods",
            "claw",
            "claw_decoder",
            "--dry-run",
            "--root",
            str(tmp_path),
        ]
    )
    out = capsys.readouterr().out
    assert out.startswith("4 runs for exp1 decoder at scale learn")  # not the decoder's controls_decoder runs
    assert sorted(line.split("--run-dir ")[1].split()[0].rsplit("/", 1)[1] for line in out.splitlines()[1:]) == [
        f"{method}__reach__F__r16__s{seed}" for method in ("claw", "claw_decoder") for seed in (2, 3)
    ]


def test_grouping_reports_incomplete_runs(tmp_path):
    runs = [
        {
            "dir": "a",
            "method": "claw",
            "family": "reach",
            "size": "I",
            "rank": 2,
            "seed": s,
            "status": "done",
            "scalars": {"eval/online/episodic_return": [(100, v), (200, v + 10)], "eval/offline/episodic_return": [(0, v)]},
        }
        for s, v in ((1, 10.0), (2, 20.0), (3, 30.0))
    ]
    runs.append(
        {
            "dir": "b",
            "method": "claw",
            "family": "reach",
            "size": "I",
            "rank": 2,
            "seed": 4,
            "status": "failed",
            "returncode": 1,
            "scalars": {},
        }
    )
    runs.append(
        {"dir": "c", "method": "claw", "family": "reach", "size": "I", "rank": 2, "seed": 5, "status": "done", "scalars": {}}
    )
    rows, curves, problems = aggregate.summarize(runs)
    online = [r for r in rows if r["metric"] == "online_return"][0]
    assert online["n"] == 3 and online["mean"] == pytest.approx(25.0) and online["seeds"] == "1,2,3"
    assert online["ci95"] == pytest.approx(mean_ci([15.0, 25.0, 35.0])[1])
    assert [c["mean"] for c in curves if c["metric"] == "online_return"] == pytest.approx([20.0, 30.0])
    assert problems == [("b", "status failed (returncode 1)"), ("c", "finished without evaluation events")]
    assert online["per_seed"] == "15,25,35" and "| 25.0 | ± 24.8 | s1: 15.0, s2: 25.0, s3: 35.0 |" in aggregate.markdown(
        rows, problems
    )
    assert "Runs not aggregated" in aggregate.markdown(rows, problems)
    # success is a Meta-World metric: a dm_control family's constant-zero success is not reported
    success_scalars = {"eval/online/episodic_return": [(100, 5.0)], "eval/online/success": [(100, 0.0)]}
    for family, expected in (("reach", {"online_return", "online_success"}), ("cheetah_walker", {"online_return"})):
        run = {
            "dir": family,
            "method": "claw",
            "family": family,
            "size": "I",
            "rank": 2,
            "seed": 1,
            "status": "done",
            "scalars": success_scalars,
        }
        rows, curves, _ = aggregate.summarize([run])
        assert {r["metric"] for r in rows} == expected and {c["metric"] for c in curves} == expected


def test_context_effect_tells_context_use_from_adaptation():
    """context_effect.py's arms on in-memory CLAW, FiLM and Concat models whose answers are known: adapters that
    do not depend on the context change predictions against the base but not between contexts, and a context
    pathway that does shows a swap change far above the same-environment one."""
    import claw_tdmpc2 as claw
    import concat_tdmpc2 as concat
    import film_tdmpc2 as film

    obs_dim, act_dim, n_rows = 5, 2, 40
    g = torch.Generator().manual_seed(0)
    with context_effect.float64():
        batches = {j: (torch.randn(32, obs_dim, generator=g), torch.rand(32, act_dim, generator=g) * 2 - 1) for j in (0, 1)}
        # each environment's context draws scatter a little around rows of their own
        typical = {j: torch.randn(n_rows, 2 * obs_dim + act_dim + 1, generator=g) for j in (0, 1)}
        contexts = {
            (j, d): typical[j] + 0.01 * torch.randn(n_rows, 2 * obs_dim + act_dim + 1, generator=g)
            for j in (0, 1)
            for d in (0, 1, 2)
        }

        def effect(method, model, hypernet, args):
            state = {
                "args": vars(args),
                "dims": (obs_dim, act_dim),
                "model": model.state_dict(),
                "hypernet": hypernet.state_dict(),
            }
            args, model, weights_for = context_effect.build(method, state)
            model.eval()
            return context_effect.context_effect(method, model, weights_for, args, batches, contexts)

        for method in (claw, film):
            torch.manual_seed(0)
            args = method.Args(model_size="I", rank=2) if method is claw else method.Args(model_size="I")
            model = method.WorldModel(obs_dim, act_dim, "I", args)
            with torch.no_grad():  # TD-MPC2 zero-initialises the reward and Q heads: every reward and Q would be 0
                model.reward.weights[-1].normal_(0, 0.1)
                model.qs.weights[-1].normal_(0, 0.1)
            layout, n_wm, n_pi = claw.lora_layout(model, 2) if method is claw else film.film_layout(model)
            template = claw.lora_template(layout, n_wm + n_pi) if method is claw else torch.zeros(n_wm + n_pi)
            hypernet = method.Hypernet(2 * obs_dim + act_dim + 1, template, args)
            # at init (A = 0 or gamma = beta = 0, generator output 0) every arm predicts exactly as the base
            at_init = effect(method, model, hypernet, args)
            assert all(v == 0 for r in at_init.values() for arm in r.values() for v in arm.values())
            # a fixed non-zero adapter: it changes predictions against the base, not between contexts
            with torch.no_grad():
                hypernet.template.normal_(0, 0.3)
            fixed = effect(method, model, hypernet, args)
            for r in fixed.values():
                assert all(v == 0 for v in r["same"].values()) and all(v == 0 for v in r["swap"].values())
                assert all(v > 1e-3 for v in r["base"].values())
            # a generator that reads u_con: environment 1's context moves predictions far more than another draw of 0's
            with torch.no_grad():
                hypernet.generator[-1].weight.normal_(0, 0.1)
            used = effect(method, model, hypernet, args)
            for r in used.values():
                assert all(r["swap"][name] > 5 * r["same"][name] > 0 for name in context_effect.OUTPUTS)
        torch.manual_seed(0)
        args = concat.Args(model_size="I")
        model, encoder = concat.WorldModel(obs_dim, act_dim, "I", args), concat.ContextEncoder(2 * obs_dim + act_dim + 1, args)
        with torch.no_grad():
            model.reward.weights[-1].normal_(0, 0.1)
            model.qs.weights[-1].normal_(0, 0.1)
        concat_effect = effect(concat, model, encoder, args)
    assert all(set(r) == {"same", "swap"} for r in concat_effect.values())  # no unconditioned Concat model
    assert all(r["swap"][name] > 5 * r["same"][name] > 0 for r in concat_effect.values() for name in context_effect.OUTPUTS)
    assert torch.get_default_dtype() == torch.float32  # float64() restores the default
    table = context_effect.markdown(used)
    assert table.count("\n") == 1 + len(context_effect.OUTPUTS) and "| swap / same |" in table


def test_end_to_end_sweep_of_two_tiny_runs(tmp_path, capsys, monkeypatch):
    runs = [r for r in sweep.plan_runs(["exp1"], "smoke") if r.method == "claw"]
    assert len(runs) == 2
    # the reports on a finished checkpoint are checked on the first run's archive only: the second run skips them
    measure = sweep.measure_checkpoint
    monkeypatch.setattr(
        sweep, "measure_checkpoint", lambda run_dir, *rest: measure(run_dir, *rest) if runs[0].name in run_dir else None
    )
    control = sweep.recipe("controls", "smoke")[0]  # evaluates runs[0]'s checkpoint: waits for it
    assert control.needs == runs[0].name
    archive = str(tmp_path / "archive")
    assert sweep.launch(runs + [control], str(tmp_path), workers=2, dry_run=False, archive=archive) == 0
    out = capsys.readouterr().out  # the control waits, then runs in the same call once its checkpoint is done
    assert f"wait (needs {runs[0].name} done) {control.name}" in out and f"ready        {control.name}" in out
    assert all(json.load(open(tmp_path / r.name / "run.json"))["status"] == "done" for r in runs + [control])
    aggregate.main([str(tmp_path)])
    summary = (tmp_path / "summary.md").read_text()
    assert "| claw | reach | I | 2 | online_return |" in summary and "| offline_return | 0 | 2 |" in summary
    rows, curves, _ = aggregate.summarize(aggregate.load_runs(str(tmp_path)))
    assert figures.figure_exp1(rows, curves, str(tmp_path)) == "exp1: no DR/ST/Oracle runs"
    assert sweep.launch(runs + [control], str(tmp_path), workers=1, dry_run=False) == 0  # a second call: nothing left
    out = capsys.readouterr().out
    assert f"skip (done)  {runs[0].name}" in out and f"skip (done)  {control.name}" in out and "ready" not in out
    result = json.load(open(tmp_path / control.name / "controls.json"))
    assert sorted(result["size"]) == ["1", "2"] and sorted(result["swap"]["own"]["offline"]) == ["0", "1"]
    assert "## Context size" in (tmp_path / control.name / "controls.md").read_text()
    # not a training run
    assert str(tmp_path / control.name) in dict(aggregate.summarize(aggregate.load_runs(str(tmp_path)))[2])
    # each finished run was archived as it ended: the archive alone aggregates to the same tables, and a launcher
    # whose sweep directory is gone (another machine) reruns nothing it holds
    assert sorted(os.listdir(archive)) == sorted(r.name for r in runs + [control])
    assert sorted(os.listdir(os.path.join(archive, control.name))) == [
        "controls.json",
        "controls.md",
        "run.json",
        "scalars.json",
        "stdout.log",
    ]
    # a finished CLAW run's archive keeps what its context does to its predictions and whether its adapters tell the
    # environments apart, both measured on the full checkpoint, and its weights
    assert sorted(os.listdir(os.path.join(archive, runs[0].name))) == [
        "checkpoint.pt",
        "context_effect.md",
        "inspect_adapters.txt",
        "run.json",
        "scalars.json",
        "stdout.log",
    ]
    effect_report = open(os.path.join(archive, runs[0].name, "context_effect.md")).read()
    assert (
        "claw_tdmpc2.py, family reach, size I; 6 environments" in effect_report
        and "| policy action |" in effect_report
        and "| swap / same |" in effect_report
    )
    adapters_report = open(os.path.join(archive, runs[0].name, "inspect_adapters.txt")).read()
    assert all(
        line in adapters_report
        for line in ("delta phi (world model)", "merged update", "gradient norms of one world-model loss")
    )
    sweep_runs, archived_runs = aggregate.load_runs(str(tmp_path)), aggregate.load_runs(archive)
    assert aggregate.summarize(archived_runs)[:2] == aggregate.summarize(sweep_runs)[:2]
    # repr: nan == nan
    assert repr(aggregate.controls_rows(archived_runs)) == repr(aggregate.controls_rows(sweep_runs)) != "[]"
    # each run once
    assert [r["dir"] for r in aggregate.load_runs([str(tmp_path / "lost"), archive, str(tmp_path)])] == [
        os.path.join(archive, r.name) for r in sorted(runs + [control], key=lambda r: r.name)
    ]
    assert sweep.launch(runs + [control], str(tmp_path / "lost"), workers=1, dry_run=False, archive=archive) == 0
    out = capsys.readouterr().out
    assert all(f"skip (archived) {r.name}" in out for r in runs + [control]) and not (tmp_path / "lost").exists()
    # a CLAW-only sweep still draws its curves
    fig_rows = [dict(r, method="dr") for r in curves]
    assert figures.figure_exp1(rows, curves + fig_rows, str(tmp_path)) is None
    assert os.path.getsize(tmp_path / "exp1.png") > 1000


def test_carried_runs_outlive_their_machine_and_archived_weights_feed_the_controls(tmp_path, capsys, monkeypatch):
    from experiments import archive as archive_module

    run = [r for r in sweep.plan_runs(["exp1"], "smoke") if r.method == "claw"][0]
    # what is carried is the training; test_end_to_end_sweep_of_two_tiny_runs covers the evaluation
    run = dataclasses.replace(run, extra=run.extra + ["--no-evaluate-after-training"])
    control = sweep.recipe("controls", "smoke")[0]
    assert control.needs == run.name
    archive, carry = str(tmp_path / "archive"), str(tmp_path / "carry")
    carried = []
    monkeypatch.setattr(sweep.RunJob, "CARRY_POLL_S", 0.1)
    # the reports measured on a finished checkpoint: test_end_to_end_sweep_of_two_tiny_runs checks them
    monkeypatch.setattr(sweep, "measure_checkpoint", lambda run_dir, method, env, flags: None)
    monkeypatch.setattr(
        sweep, "carry_run", lambda run_dir, to: carried.append(run_dir) or archive_module.carry_run(run_dir, to)
    )
    first = tmp_path / "first"  # a machine that trains the run, then is lost
    assert sweep.launch([run], str(first), workers=1, dry_run=False, archive=archive, carry=carry) == 0
    # copied while it ran (each time it saved progress), removed once archived
    assert carried and set(carried) == {str(first / run.name)} and os.listdir(carry) == []
    # the archive keeps the weights, not what only training resumes from
    weights = torch.load(os.path.join(archive, run.name, "checkpoint.pt"), weights_only=False)
    full = torch.load(first / run.name / "checkpoint.pt", weights_only=False)
    assert weights["replay"] is None and weights["optimizers"] is None and full["replay"] is not None
    assert all(torch.equal(weights["model"][k], v) for k, v in full["model"].items())
    # a second machine: the controls evaluate the archived weights, without retraining the run
    second = tmp_path / "second"
    assert sweep.launch([run, control], str(second), workers=1, dry_run=False, archive=archive, carry=carry) == 0
    out = capsys.readouterr().out
    assert f"restored     {os.path.join(archive, run.name)} -> {second}" in out and f"skip (archived) {run.name}" in out
    assert sweep.read_status(str(second / control.name))["status"] == "done" and sweep.is_archived(archive, control.name)
    # an unfinished run's carried copy resumes from its checkpoint on a third machine, then leaves the carry directory
    record = sweep.read_status(str(first / run.name))
    sweep.write_status(str(first / run.name), run, shlex.split(record["command"]), "interrupted")
    for name in os.listdir(archive):
        shutil.rmtree(os.path.join(archive, name))
    assert archive_module.archive_sweep(str(first), archive, carry) == 0 and os.listdir(carry) == [run.name]
    assert "run.lock" not in os.listdir(os.path.join(carry, run.name))
    third = tmp_path / "third"
    assert sweep.launch([run], str(third), workers=1, dry_run=True, archive=archive, carry=carry) == 0
    assert f"would restore {os.path.join(carry, run.name)}" in capsys.readouterr().out and not third.exists()
    assert sweep.launch([run], str(third), workers=1, dry_run=False, archive=archive, carry=carry) == 0
    out = capsys.readouterr().out
    assert f"restored     {os.path.join(carry, run.name)} -> {third}" in out and "resume " in out
    assert sweep.read_status(str(third / run.name))["resumed"] is True and sweep.is_archived(archive, run.name)
    assert os.listdir(carry) == []
    with pytest.raises(SystemExit, match="--carry needs --archive"):
        sweep.main(["exp1", "--scale", "smoke", "--carry", carry, "--dry-run"])


def test_controls_recipe_evaluates_the_exp12_claw_checkpoints_once_they_are_done(tmp_path, capsys):
    controls = sweep.recipe("controls", "learn")
    families = ("go1", "push", "reach", "walker")
    assert sorted((r.family, r.seed) for r in controls) == [(f, s) for f in families for s in (1, 2, 3)]
    for run in controls:
        trained = sweep.Run("claw", run.family, "F", 16, run.seed)
        run_dir = tmp_path / run.name
        command = run.command(str(run_dir))
        assert run.needs == trained.name and command[1].endswith("diagnostics/context_controls.py")
        assert command[2] == str(tmp_path / trained.name / "checkpoint.pt")
        assert command[-4:] == ["--json", str(run_dir / "controls.json"), "--out", str(run_dir / "controls.md")]
        assert (
            command[command.index("--eval-episodes") + 1]
            == {"reach": "10", "walker": "2", "push": "10", "go1": "2"}[run.family]
        )
        if run.family == "walker":  # a distant strength, not the neighbouring one
            assert command[command.index("--swap-offset") + 1] == "10"
        assert "--compile" in command and "--seed" not in command and "--no-cuda" not in command  # the checkpoint's own
    planned = sweep.plan_runs(["controls", "exp1"], "smoke")  # training first, whatever the order asked
    assert [r.method for r in planned][-2:] == ["controls", "controls"] and "controls" not in [r.method for r in planned[:-2]]
    control = planned[-1]
    trained = next(r for r in planned if r.name == control.needs)
    for status in (None, "running", "failed", "done"):
        if status:
            sweep.write_status(str(tmp_path / trained.name), trained, trained.command(str(tmp_path / trained.name)), status)
        pending = sweep.pending_runs([control], str(tmp_path))
        out = capsys.readouterr().out
        if status != "done":
            assert pending == [] and out == f"wait (needs {trained.name} done) {control.name}\n"
        else:
            assert pending == [(control, str(tmp_path / control.name))]
            assert out == "run    " + sweep.shlex.join(control.command(str(tmp_path / control.name))) + "\n"
    pending = sweep.pending_runs(planned, str(tmp_path))  # a ready controls run is queued first
    waiting = next(r for r in planned if r.method == "controls" and r is not control)
    assert [r.name for r, _ in pending][0] == control.name and len(pending) == len(planned) - 2  # its CLAW run: done
    assert f"wait (needs {waiting.needs} done) {waiting.name}" in capsys.readouterr().out
    sweep.main(["exp1", "controls", "--scale", "smoke", "--dry-run", "--root", str(tmp_path / "cli")])
    assert capsys.readouterr().out.count("wait (needs claw__reach__I__r2__s") == 2


def test_context_identifiability_statistics_on_synthetic_contexts():
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, (200, 39))
    reward = 2.0 + obs[:, 0] - 3.0 * obs[:, 2]  # linear in the hand position (obs[:, :3])
    mean, slope = context_identifiability.context_features({"reward": reward, "next_obs": obs}, "reach")
    assert mean == pytest.approx([reward.mean()])
    assert slope == pytest.approx([1.0, 0.0, -3.0], abs=1e-9)
    labels = np.repeat(np.arange(3), 4)
    separable = labels[:, None] * 10.0 + rng.normal(0, 0.1, (12, 1))
    assert context_identifiability.nearest_centroid_accuracy(separable, labels) == 12
    assert context_identifiability.nearest_centroid_accuracy(rng.normal(size=(12, 1)), labels) < 12


def test_decoder_signal_separates_what_the_environment_changes():
    """Two synthetic environments: the reward shifts with the environment, the dynamics do not (and vice versa)."""
    rng = np.random.default_rng(0)

    def environment(env_id, reward_shift, dynamics_gain):
        obs, action = rng.uniform(-1, 1, (1500, 3)).astype(np.float32), rng.uniform(-1, 1, (1500, 1)).astype(np.float32)
        next_obs = obs + (1.0 + dynamics_gain * env_id) * action + rng.normal(0, 0.2, obs.shape).astype(np.float32)
        reward = np.sin(next_obs[:, 0]) + reward_shift * env_id + rng.normal(0, 0.2, 1500).astype(np.float32)
        return {"obs": obs, "action": action, "next_obs": next_obs, "reward": reward}

    goals = decoder_signal.signal([environment(j, reward_shift=1.0, dynamics_gain=0.0) for j in (0, 1)], steps=300)
    strengths = decoder_signal.signal([environment(j, reward_shift=0.0, dynamics_gain=1.0) for j in (0, 1)], steps=300)
    assert goals["reward"][3] > 0.5 and abs(goals["next state"][3]) < 0.3
    assert strengths["next state"][3] > 0.5 and abs(strengths["reward"][3]) < 0.3


def test_encoder_probe_learns_a_goal_that_shifts_the_reward():
    rng = np.random.default_rng(1)

    def contexts(label, count):  # 20 transitions of width 83 (reach's 2*39+4+1); reward column shifted by label
        rows = [rng.normal(size=(20, 83)).astype(np.float32) for _ in range(count)]
        for r in rows:
            r[:, 43] += 3.0 * label
        return [torch.as_tensor(r) for r in rows]

    train = contexts(0, 4) + contexts(1, 4)
    test = contexts(0, 3) + contexts(1, 3)
    draw = lambda step: [train[step % 4], train[4 + step % 4]]  # noqa: E731
    hits, ratio = context_identifiability.train_encoder_probe(
        draw, [0, 1], test, [0] * 3 + [1] * 3, steps=60, statistics=torch.cat(train)
    )
    assert hits == 6 and ratio > 1.5


def test_learn_recipes_and_budget_training_curves(monkeypatch):
    """The budget recipe trains ST on each Cheetah/Walker embodiment, one Push goal and Go1 forward (distinct run names);
    its runs are aggregated as training curves per step window and embodiment, seeds averaged, and Exp 3-5 wait for the
    chosen budget."""
    budget = sweep.recipe("budget", "learn")
    assert sorted((r.family, r.train_env, r.seed) for r in budget) == [
        ("cheetah_walker", 0, 1),
        ("cheetah_walker", 0, 2),
        ("cheetah_walker", 1, 1),
        ("cheetah_walker", 1, 2),
        ("go1", 0, 1),
        ("go1", 0, 2),
        ("push", 0, 1),
        ("push", 0, 2),
    ]
    assert len({r.name for r in budget}) == 8 and all("--train-env-id" in r.command("d") for r in budget)
    steps = {r.family: r.extra[r.extra.index("--total-timesteps") + 1] for r in budget}
    assert steps == {"cheetah_walker": "40000", "push": "100000", "go1": "100000"}
    exp12 = sweep.plan_runs(["exp1", "exp2"], "learn")
    assert {(r.family, r.size) for r in exp12} == {(f, "F") for f in ("reach", "walker", "go1", "push")} and len(
        exp12
    ) == 4 * 4 * 3
    exp12_steps = {r.family: r.extra[r.extra.index("--total-timesteps") + 1] for r in exp12 if "--total-timesteps" in r.extra}
    assert exp12_steps["push"] == "40000" and exp12_steps["go1"] == "70000"  # the budgets the curves chose
    decoder_and_controls = sweep.plan_runs(["decoder"], "learn")  # Exp 1/2's CLAW runs with --decoder-coef, named apart
    decoder = [r for r in decoder_and_controls if r.method == "claw_decoder"]
    controls = sweep.plan_runs(["controls"], "learn")
    # each followed by the controls experiment's evaluation of its checkpoint
    assert [(r.method, r.needs, r.extra) for r in decoder_and_controls[len(decoder) :]] == [
        ("controls_decoder", trained.name, r.extra) for trained, r in zip(decoder, controls)
    ]
    assert [r.command("d")[1:2] + r.command("d")[3:] for r in decoder_and_controls[len(decoder) :]] == [
        r.command("d")[1:2] + r.command("d")[3:] for r in controls
    ]
    claw12 = [r for r in exp12 if r.method == "claw"]
    assert [(r.family, r.seed) for r in decoder] == [(r.family, r.seed) for r in claw12]
    assert all(
        r.command("d")[1].endswith("claw_tdmpc2.py") and r.command("d")[-2:] == ["--decoder-coef", "1.0"] for r in decoder
    )
    assert [r.command("d")[:-2] for r in decoder] == [r.command("d") for r in claw12]
    assert not {r.name for r in decoder} & {r.name for r in exp12}
    exp45 = sweep.plan_runs(["exp4", "exp5"], "learn")  # at the budget chosen from the curves: 2 x 20,000 steps
    assert sorted({(r.method, r.rank) for r in exp45}) == [
        ("claw", 1),
        ("claw", 4),
        ("claw", 8),
        ("claw", 16),
        ("concat", 8),
        ("film", 8),
        ("posthoc", 8),
    ]
    assert len(exp45) == 7 * 3 and all(r.size == "F" and "40000" in r.extra for r in exp45)
    # seed-major across experiments: every experiment's first seed before any second seed
    learn_runs = sweep.plan_runs(["exp4", "exp5", "exp1", "exp2", "controls"], "learn")
    seed1 = [r for r in learn_runs if r.seed == 1 and r.needs is None]
    assert [r.seed for r in learn_runs if r.needs is None] == sorted(r.seed for r in learn_runs if r.needs is None)
    assert {m for r in seed1 for m in r.experiments} == {"exp1", "exp2", "exp4", "exp5"}
    without_budget = {k: v for k, v in sweep.SCALES["learn"].items() if k != "exp345"}
    monkeypatch.setitem(sweep.SCALES, "learn", without_budget)
    with pytest.raises(SystemExit, match="waits for its per-embodiment budget"):
        sweep.recipe("exp4", "learn")
    monkeypatch.setattr(aggregate, "random_policy_return", lambda family, env_id: 10.0 * (env_id + 1))

    def run(env_id, seed, returns):  # (step, training-episode return) pairs, as TensorBoard holds them
        return {
            "method": "st",
            "family": "cheetah_walker",
            "size": "F",
            "seed": seed,
            "experiments": ["budget"],
            "command": f"python st_tdmpc2.py --train-env-id {env_id}",
            "scalars": {"charts/episodic_return": returns},
        }

    # no training episode yet: no curve
    runs = [
        run(0, 1, [(3000, 10.0), (5000, 30.0), (5500, 50.0)]),
        run(0, 2, [(4000, 20.0), (6000, 70.0)]),
        run(1, 1, [(2600, 5.0)]),
        {"method": "claw", "family": "cheetah_walker", "size": "F", "seed": 1, "experiments": ["exp1"], "scalars": {}},
    ]
    rows = aggregate.training_curves(runs, window=2500)
    assert [(r["train_env"], r["step"], r["n"], r["mean"]) for r in rows] == [
        (0, 5000, 2, 20.0),
        (0, 7500, 2, 60.0),
        (1, 5000, 1, 5.0),
    ]
    assert [r["random_policy"] for r in rows] == [10.0, 10.0, 20.0]
    assert "| 7500 | 2 | 60.0 |" in aggregate.training_markdown(rows)


def test_random_policy_return_is_a_real_rollout():
    first = aggregate.random_policy_return("reach", 0, episodes=2)
    again = aggregate.random_policy_return.__wrapped__("reach", 0, episodes=2)  # a second rollout, not the cached value
    assert first == again and first != 0.0
    assert aggregate.random_policy_return("reach", 0, episodes=2, seed=1) != first


def test_a_familys_random_reference_averages_its_environments_over_about_twenty_episodes(monkeypatch):
    calls, family_mean = [], aggregate.random_policy_return.__wrapped__  # uncached; its per-environment calls recorded
    monkeypatch.setattr(aggregate, "random_policy_return", lambda f, j, episodes, seed: calls.append(episodes) or 10.0 * j)
    assert (family_mean("go1", "all"), calls) == (5.0, [10, 10])  # a direction's reference is the per-direction one
    calls.clear()
    assert (family_mean("reach", "all"), calls) == (25.0, [4] * 6)
    calls.clear()
    assert (family_mean("walker", "all"), calls) == (95.0, [2] * 20)


def test_context_probes_patch_claw_only_while_they_run(monkeypatch):
    import claw_tdmpc2 as claw
    from common.envs import make_env
    from diagnostics import context_probes

    plain_forward, plain_collect = claw.ContextEncoder.forward, claw.collect_episodes

    def fake_main(args):  # what the patched script's hypernetwork would embed, and the contexts it would see
        encoder = claw.ContextEncoder(10, args)
        env = make_env("reach", 2)
        context = claw.collect_episodes(env, 1, seed=0)
        seen.append((args.context_dim, encoder(torch.randn(50, 10) * 5 + 3), env.unwrapped.goal, context))

    seen = []
    monkeypatch.setattr(claw, "main", fake_main)
    context_probes.main(["unorm", "train", "--context-dim", "16"])
    context_probes.main(["goal", "train", "--context-dim", "16"])
    (dim, u_con, _, plain_context), (_, u_con_goal, goal, goal_context) = seen
    assert dim == 16 and float(u_con.mean()) == pytest.approx(0.0, abs=1e-5)
    assert float(u_con.var(unbiased=False)) == pytest.approx(1.0, rel=1e-3)
    assert float(u_con_goal.var(unbiased=False)) != pytest.approx(1.0, rel=1e-3)  # the goal probe leaves u_con alone
    assert not plain_context["obs"][:, 36:39].any()  # the unorm probe leaves the contexts alone
    assert np.allclose(goal_context["next_obs"][:, 36:39], goal) and np.allclose(goal_context["obs"][:, 36:39], goal)
    assert np.array_equal(np.delete(goal_context["obs"], np.s_[36:39], 1), np.delete(plain_context["obs"], np.s_[36:39], 1))
    assert (claw.ContextEncoder.forward, claw.collect_episodes) == (plain_forward, plain_collect)  # restored afterwards
    with pytest.raises(SystemExit, match="Meta-World family"):
        context_probes.goal_revealing_collect(make_env("walker", 0), 1, seed=0)
    with pytest.raises(
        SystemExit, match=r"takes a probe \(unorm, goal\) and a tool \(train, inspect, controls\), got goal bogus"
    ):
        context_probes.main(["goal", "bogus"])


def test_figure_intervals_stay_within_what_the_metric_can_take():
    # at n = 2 (t = 12.7) mean +- CI crosses 0 and 1: the figures cut bands and error bars there
    lower, upper = figures._interval("online_success", [{"mean": 0.9, "ci95": 0.5}, {"mean": 0.1, "ci95": 0.05}])
    assert lower == pytest.approx([0.4, 0.05]) and upper == pytest.approx([1.0, 0.15])
    assert figures._interval("offline_return", [{"mean": 100.0, "ci95": 300.0}]) == ([0.0], [400.0])
    assert figures._yerr("offline_return", [{"mean": 100.0, "ci95": 300.0}]) == [[100.0], [300.0]]
    # one seed has no interval: NaN, which matplotlib does not draw (0 would draw a cap that reads as a tight interval)
    for no_ci in (float("nan"), None):
        (low,), (high,) = figures._yerr("offline_return", [{"mean": 100.0, "ci95_seeds": no_ci}], "ci95_seeds")
        assert math.isnan(low) and math.isnan(high)


def test_one_seed_figures_draw_no_error_bars_and_say_n(tmp_path, monkeypatch):
    rows = [
        {
            "method": m,
            "family": "cheetah_walker",
            "size": "F",
            "rank": 8,
            "metric": "online_return_env0",
            "n": 1,
            "mean": v,
            "ci95": float("nan"),
        }
        for m, v in (("claw", 190.0), ("posthoc", 25.0))
    ]
    saved = []
    monkeypatch.setattr(figures.plt.Figure, "savefig", lambda fig, path, **kwargs: saved.append(fig))

    def drawn_error_bars():  # of the last figure: matplotlib keeps a NaN error bar as an empty segment
        ax = saved[-1].axes[0]
        bars = [c for c in ax.containers if isinstance(c, figures.matplotlib.container.ErrorbarContainer)]
        assert bars
        return ax.get_title(), [
            seg for c in bars for coll in c.lines[2] for seg in coll.get_segments() if np.isfinite(seg).any()
        ]

    assert figures.figure_exp5(rows, [], str(tmp_path)) is None
    assert drawn_error_bars() == ("size F, rank 8, n = 1", [])
    rows[1].update(n=3, ci95=5.0)  # with an interval, the bar gets one
    figures.figure_exp5(rows, [], str(tmp_path))
    title, drawn = drawn_error_bars()
    assert title == "size F, rank 8, n = 1-3" and len(drawn) == 1 and np.allclose(drawn[0][:, 1], [20, 30])
