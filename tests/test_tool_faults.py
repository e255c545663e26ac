"""Bad input to the tools (experiments/aggregate.py, figures.py and the checkpoint diagnostics): one line naming the file or
flag and what is wrong, a non-zero exit status, nothing written; a damaged run in a sweep is named and left out while
the rest aggregates. The checkpoints here are hand-made dicts: every refusal happens before a weight is read."""

import json
import os

import pytest
import torch

from diagnostics import (
    context_controls,
    context_effect,
    context_identifiability,
    context_probes,
    decoder_signal,
    inspect_adapters,
    oracle_controls,
)
from experiments import aggregate, figures
from experiments.archive import archive_sweep, save_weights

# (tool, the methods whose checkpoints it reads, the training state it needs beyond the weights)
CHECKPOINT_TOOLS = [
    (inspect_adapters, "claw_tdmpc2.py", "replay buffer and context pool"),
    (context_effect, "claw_tdmpc2.py", "replay buffer"),
    (context_controls, "claw_tdmpc2.py", None),
    (oracle_controls, "oracle_tdmpc2.py", None),
]


def refused(main, argv) -> str:
    """main(argv)'s SystemExit message: one line, a non-zero exit status (a string code exits with 1)."""
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    message = str(stopped.value.code)
    assert stopped.value.code not in (0, None) and message.startswith("error: ") and "\n" not in message, message
    return message


def checkpoint(path, method: str, **state) -> str:
    args = {"family": "reach", "model_size": "I", "rank": 2}
    torch.save({"args": args, "dims": (39, 4), "model": {}, "method": method, **state}, path)
    return str(path)


@pytest.mark.parametrize("tool, method, needs", CHECKPOINT_TOOLS, ids=lambda t: getattr(t, "__name__", None))
def test_a_checkpoint_tool_names_the_file_and_what_is_wrong(tool, method, needs, tmp_path):
    name = tool.__name__.split(".")[-1] + ".py"
    missing = tmp_path / "missing.pt"
    assert refused(tool.main, [str(missing)]) == f"error: checkpoint {missing} does not exist"
    assert refused(tool.main, [str(tmp_path)]) == (
        f"error: {tmp_path} is a directory; {name} reads a checkpoint file (e.g. {tmp_path}/checkpoint.pt)"
    )
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint\n")
    assert refused(tool.main, [str(text)]).startswith(f"error: cannot read checkpoint {text} (truncated, corrupt or not a")
    whole = checkpoint(tmp_path / "whole.pt", method, replay={}, contexts=([], 0))
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(open(whole, "rb").read()[:200])
    assert "PytorchStreamReader failed" in refused(tool.main, [str(truncated)])
    torch.save([1, 2], tmp_path / "list.pt")
    assert refused(tool.main, [str(tmp_path / "list.pt")]).endswith(
        "list.pt is not a checkpoint of the method scripts (no saved 'args' and 'model')"
    )
    dr = checkpoint(tmp_path / "dr.pt", "dr_tdmpc2.py")
    wanted = "CLAW" if method == "claw_tdmpc2.py" else "Oracle"
    assert refused(tool.main, [dr]).startswith(
        f"error: {dr} is a checkpoint of DR (dr_tdmpc2.py); {name} needs a checkpoint of {wanted}"
    )
    archived = str(tmp_path / "archived.pt")
    save_weights(whole, archived)  # as experiments/archive.py keeps a finished run's checkpoint
    if needs is None:  # evaluation reads the weights alone: the archived checkpoint passes the checks
        with pytest.raises(SystemExit, match="does not fit this configuration"):
            tool.main([archived])
    else:
        assert refused(tool.main, [archived]) == (
            f"error: {archived} is weights only, as archived checkpoints are (no {needs.replace(' and ', ' or ')}); "
            f"{name} needs the {needs}: give it the run's full checkpoint.pt from its run directory"
        )


FLAGS = [
    (inspect_adapters, ["--draws", "1"], "--draws must be >= 2, got 1"),
    (inspect_adapters, ["--episodes", "0"], "--episodes must be >= 1, got 0"),
    (context_effect, ["--batch", "0"], "--batch must be >= 1, got 0"),
    (context_effect, ["--draws", "1"], "--draws must be >= 2, got 1"),
    (context_controls, ["--context-episodes", "3", "0"], "--context-episodes must be >= 1, got 0"),
    (context_controls, ["--eval-episodes", "0"], "--eval-episodes must be >= 1, got 0"),
    (context_controls, ["--online-eval-steps", "-5"], "--online-eval-steps must be >= 0, got -5"),
    (context_controls, ["--threads", "0"], "--threads must be >= 1, got 0"),
    (oracle_controls, ["--eval-episodes", "0"], "--eval-episodes must be >= 1, got 0"),
    (oracle_controls, ["--env-ids", "0", "-1"], "--env-ids must be >= 0, got -1"),
]


@pytest.mark.parametrize("tool, flags, message", FLAGS, ids=lambda x: " ".join(x) if isinstance(x, list) else None)
def test_a_checkpoint_tools_flags_are_checked_before_the_checkpoint_is_read(tool, flags, message, tmp_path):
    assert refused(tool.main, [str(tmp_path / "never_read.pt"), *flags]) == f"error: {message}"


@pytest.mark.parametrize(
    "tool, argv, message",
    [
        (decoder_signal, ["--steps", "0"], "error: --steps must be >= 1, got 0"),
        (decoder_signal, ["--episodes", "0"], "error: --episodes must be >= 1, got 0"),
        (decoder_signal, ["--seed", "-1"], "error: --seed must be >= 0, got -1"),
        (context_identifiability, ["--draws", "1"], "error: --draws must be >= 2, got 1"),
        (context_identifiability, ["--probe-refresh", "-1"], "error: --probe-refresh must be >= 0, got -1"),
        (
            context_identifiability,
            ["--probe-pool", "2"],
            "error: --probe-pool must be >= --context-episodes (3): a probe context draws that many episodes from the "
            "pool, got 2",
        ),
        (context_probes, ["goal", "plot"], "error: context_probes.py takes a probe (unorm, goal) and a tool (train, "),
    ],
    ids=lambda x: " ".join(x) if isinstance(x, list) else None,
)
def test_the_other_diagnostics_check_their_flags_before_any_rollout(tool, argv, message):
    assert refused(tool.main, argv).startswith(message)


def archived_run(root, name, method="claw", seed=1, **overrides) -> str:
    """An archived run (run.json and scalars.json, as experiments/archive.py writes them) with one Exp 1 return."""
    run_dir = os.path.join(root, name)
    os.makedirs(run_dir)
    record = {"method": method, "family": "reach", "size": "I", "rank": 2, "seed": seed, "status": "done", **overrides}
    with open(os.path.join(run_dir, "run.json"), "w") as f:
        json.dump(record, f)
    with open(os.path.join(run_dir, "scalars.json"), "w") as f:
        json.dump({"scalars": {"eval/online/episodic_return": [[100, 10.0 * seed]]}, "duplicated": []}, f)
    return run_dir


def damaged_sweep(root) -> dict:
    """Two sound runs and one damaged run of each kind; {run name: the words its warning must hold}."""
    for seed in (1, 2):
        archived_run(root, f"claw__reach__I__r2__s{seed}", seed=seed)
    truncated = archived_run(root, "claw__reach__I__r2__s3", seed=3)
    text = open(os.path.join(truncated, "run.json")).read()
    open(os.path.join(truncated, "run.json"), "w").write(text[: len(text) // 2])
    archived_run(root, "claw__reach__I__r2__s4", seed=4)
    with open(os.path.join(root, "claw__reach__I__r2__s4", "run.json"), "w") as f:
        json.dump({"method": "claw", "status": "done"}, f)
    invalid = archived_run(root, "claw__reach__I__r2__s5", seed=5)
    open(os.path.join(invalid, "scalars.json"), "w").write('{"scalars": {"eval/online/episodic_return": 5}, "duplicated": []}')
    listed = archived_run(root, "claw__reach__I__r2__s6", seed=6)
    open(os.path.join(listed, "run.json"), "w").write("[]")
    controls = archived_run(root, "controls__reach__I__r2__s1", method="controls")
    open(os.path.join(controls, "controls.json"), "w").write('{"context_episodes": 1, "swa')
    return {
        "claw__reach__I__r2__s3": "run.json: not readable JSON (truncated or damaged: Expecting value",
        "claw__reach__I__r2__s4": "run.json: lacks family, size, rank, seed",
        "claw__reach__I__r2__s5": "scalars.json: scalars are not {tag: [[step, value], ...]}",
        "claw__reach__I__r2__s6": "run.json: a JSON list, expected an object",
    }


def test_aggregate_names_each_damaged_run_and_aggregates_the_rest(tmp_path, capsys):
    damaged = damaged_sweep(str(tmp_path))
    aggregate.main([str(tmp_path)])
    out, err = capsys.readouterr()
    warnings = err.splitlines()
    for name, why in damaged.items():
        line = next(line for line in warnings if name in line)
        assert line.startswith(f"warning: skipped a damaged run: {tmp_path / name}/") and why in line, line
        assert line.endswith("; the other runs go on")
    controls = tmp_path / "controls__reach__I__r2__s1" / "controls.json"
    assert f"warning: skipped the controls of controls__reach__I__r2__s1: {controls}: not readable JSON" in err
    summary = (tmp_path / "summary.md").read_text()
    assert "| claw | reach | I | 2 | online_return |  | 2 | 15.0 |" in summary  # seeds 1 and 2 alone
    assert all(f"- `{name}`: damaged: " in summary for name in damaged)
    assert "7 runs, 5 not aggregated" in out  # the damaged four and the controls run (evaluation only)


def test_archiving_names_each_damaged_run_and_archives_the_rest(tmp_path, capsys):
    damaged = damaged_sweep(str(tmp_path / "sweep"))
    assert archive_sweep(str(tmp_path / "sweep"), str(tmp_path / "archive")) == 3  # seeds 1, 2 and the controls run
    out = capsys.readouterr().out
    for name, why in damaged.items():
        assert f"warning: not archived: {tmp_path / 'sweep' / name}/" in out and why in out
    assert sorted(os.listdir(tmp_path / "archive")) == [
        "claw__reach__I__r2__s1",
        "claw__reach__I__r2__s2",
        "controls__reach__I__r2__s1",
    ]


def test_figures_names_each_damaged_run_and_draws_from_the_rest(tmp_path, capsys):
    damaged = damaged_sweep(str(tmp_path / "sweep"))
    figures.main([str(tmp_path / "sweep"), "--out", str(tmp_path / "figures")])
    out, err = capsys.readouterr()
    assert all(f"warning: skipped a damaged run: {tmp_path / 'sweep' / name}/" in err for name in damaged)
    assert "skipped exp1: no DR/ST/Oracle runs" in out and os.path.isdir(tmp_path / "figures")


def test_a_sweep_path_that_does_not_exist_is_refused_and_not_created(tmp_path):
    missing = tmp_path / "no_such_sweep"
    for tool in (aggregate, figures):
        name = tool.__name__.split(".")[-1] + ".py"
        assert refused(tool.main, [str(missing)]) == (
            f"error: {missing} does not exist; {name} reads sweep directories or archives (e.g. runs/sweeps/cpu)"
        )
        assert not missing.exists()
    (tmp_path / "file").write_text("")
    assert refused(figures.main, [str(tmp_path / "file")]).endswith(
        "file is not a directory; figures.py reads sweep directories or archives (e.g. runs/sweeps/cpu)"
    )
    archived_run(str(tmp_path / "sweep"), "claw__reach__I__r2__s1")
    assert refused(figures.main, [str(tmp_path / "sweep"), "--out", str(tmp_path / "file")]) == (
        f"error: --out {tmp_path / 'file'} is a file; figures.py writes its PNGs into a directory"
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    assert refused(aggregate.main, [str(empty)]).startswith(f"error: no run.json under {empty}; aggregate.py needs runs")
    damaged_only = tmp_path / "damaged_only"
    archived_run(str(damaged_only), "claw__reach__I__r2__s1")
    (damaged_only / "claw__reach__I__r2__s1" / "run.json").write_text("{")
    assert refused(figures.main, [str(damaged_only)]).startswith(
        f"error: no readable run.json (1 damaged) under {damaged_only}"
    )
    assert os.listdir(damaged_only) == ["claw__reach__I__r2__s1"]  # no figure written


def test_the_launcher_resumes_a_run_whose_run_json_is_damaged_and_stops_on_a_damaged_archive(tmp_path, capsys):
    from experiments import sweep

    run = sweep.plan_runs(["exp1"], "smoke")[0]
    root, archive = tmp_path / "sweep", tmp_path / "archive"
    os.makedirs(root / run.name)
    (root / run.name / "run.json").write_text('{"method": "cl')
    assert [pending.name for pending, _ in sweep.pending_runs([run], str(root))] == [run.name]
    assert f"warning: {root / run.name / 'run.json'}: not readable JSON" in capsys.readouterr().out
    os.makedirs(archive / run.name)
    (archive / run.name / "run.json").write_text("[]")
    with pytest.raises(SystemExit) as stopped:
        sweep.pending_runs([run], str(root), archive=str(archive))
    assert str(stopped.value.code).startswith(f"error: archived run damaged: {archive / run.name / 'run.json'}")
