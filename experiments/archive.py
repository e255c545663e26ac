"""What a finished sweep run measured, kept without its training state in a directory small enough to commit.

A sweep directory lives on one machine, beside multi-megabyte checkpoints; an archive keeps each finished run's
measurements where losing that machine cannot take them. An archived run is its run.json, its TensorBoard scalars as
JSON (scalars.json), its stdout.log, for an in-context method's run context_effect.md (`context_effect.py`: how much
the context moves the world model's predictions, measured on the checkpoint), for a CLAW run inspect_adapters.txt
(`inspect_adapters.py`: do u_con and the adapters tell the environments apart) and, for the context controls,
controls.json and controls.md, and its checkpoint as weights only (WEIGHTS: no replay buffer, optimizer state or
context pool; for evaluation: the context controls of a CLAW run whose sweep directory is gone, re-measured
reports, new evaluation-only analyses). `aggregate.py` and `figures.py` read an archive like a sweep directory, and
`sweep.py --archive DIR` archives each run as it finishes and skips the runs the archive holds.

A run longer than a machine lives is carried: with `sweep.py --carry DIR` the launcher copies a live run's directory
(checkpoint, evaluation progress, events, stdout.log; mostly the replay buffer and context pool) to DIR/<run> each
time the run saves progress, removes the copy once the run is archived, and, on a machine whose sweep directory lacks
the run, copies DIR/<run> back before launching: the run resumes from its last checkpoint.

    python experiments/archive.py runs/sweeps/learn results/learn/runs   # archive every finished run of a sweep
    python experiments/archive.py runs/sweeps/learn results/learn/runs --carry results/learn/carry   # and carry the others
    python experiments/archive.py --slim results/learn/runs   # rewrite an archive's checkpoints as weights only
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys

SCALARS = "scalars.json"
# copied as they are, where the run wrote them
KEPT = ("stdout.log", "context_effect.md", "inspect_adapters.txt", "controls.json", "controls.md")
WEIGHTS = "checkpoint.pt"  # in the archive: the run's checkpoint less what only training resumes from
TRAINING_ONLY = ("replay", "optimizers", "contexts")  # kept as None: weights only
NOT_CARRIED = ("run.lock",)  # and the half-written files: *.tmp, *.partial
RUN_KEYS = ("method", "family", "size", "rank", "seed", "status")  # what sweep.py writes in every run.json


class DamagedRun(ValueError):
    """A run file that cannot be read: its message is one line naming the file and what is wrong."""


def read_json(path: str, required=()) -> dict:
    """A JSON object from path, or DamagedRun: unreadable, truncated or invalid JSON, not an object, or lacking a
    required key."""
    try:
        with open(path) as f:
            record = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DamagedRun(f"{path}: not readable JSON (truncated or damaged: {error})") from None
    if not isinstance(record, dict):
        raise DamagedRun(f"{path}: a JSON {type(record).__name__}, expected an object")
    missing = [key for key in required if key not in record]
    if missing:
        raise DamagedRun(f"{path}: lacks {', '.join(missing)}")
    return record


def read_scalars(run_dir: str) -> tuple[dict, list]:
    """({tag: [(step, value), ...]} sorted by step, [tags that repeat a step]) from an archived run's scalars.json,
    else from the run's TensorBoard events (where a step repeats, the last value wins, as in TensorBoard).
    DamagedRun for a scalars.json that is not what archive_run writes."""
    path = os.path.join(run_dir, SCALARS)
    if os.path.isfile(path):
        archived = read_json(path, ("scalars", "duplicated"))
        try:
            return {
                tag: [(int(step), float(value)) for step, value in points] for tag, points in archived["scalars"].items()
            }, list(archived["duplicated"])
        except (AttributeError, TypeError, ValueError) as error:
            raise DamagedRun(f"{path}: scalars are not {{tag: [[step, value], ...]}} ({error})") from None
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    # a resumed run's writer starts with purge_step: TensorBoard drops the steps the killed process logged after
    # its checkpoint, as intended, and warns "Detected out of order event.step" for each such file
    tensorboard_logger = logging.getLogger("tensorboard")
    level = tensorboard_logger.level
    tensorboard_logger.setLevel(logging.ERROR)
    try:
        events = EventAccumulator(run_dir, size_guidance={"scalars": 0}).Reload()
        scalars, duplicated = {}, []
        for tag in events.Tags()["scalars"]:
            steps = [(e.step, e.value) for e in events.Scalars(tag)]
            if len({step for step, _ in steps}) < len(steps):  # e.g. a resume logged without purge_step
                duplicated.append(tag)
            scalars[tag] = sorted(dict(steps).items())
    finally:
        tensorboard_logger.setLevel(level)
    return scalars, duplicated


def archive_run(run_dir: str, archive: str) -> str:
    """Copies a finished run's measurements to archive/<run name>/ (replacing an older copy); returns that path."""
    with open(os.path.join(run_dir, "run.json")) as f:
        record = json.load(f)
    if record.get("status") != "done":
        raise ValueError(f"{run_dir}: status {record.get('status')!r}; only finished runs are archived")
    target = os.path.join(archive, os.path.basename(os.path.normpath(run_dir)))
    staging = target + ".tmp"
    scalars, duplicated = read_scalars(run_dir)  # first: a damaged run leaves no half-made copy behind
    shutil.rmtree(staging, ignore_errors=True)
    os.makedirs(staging)
    with open(os.path.join(staging, SCALARS), "w") as f:
        json.dump({"scalars": scalars, "duplicated": duplicated}, f, separators=(",", ":"))
    for name in KEPT:
        if os.path.isfile(os.path.join(run_dir, name)):
            shutil.copy2(os.path.join(run_dir, name), staging)
    if os.path.isfile(os.path.join(run_dir, WEIGHTS)):
        save_weights(os.path.join(run_dir, WEIGHTS), os.path.join(staging, WEIGHTS))
    shutil.copy2(os.path.join(run_dir, "run.json"), staging)  # last: a copy with run.json is complete
    replace_dir(staging, target)
    return target


def save_weights(checkpoint: str, path: str) -> None:
    """The checkpoint as weights only (no replay buffer, optimizer state or context pool): --eval-only and the
    evaluation tools read it as the full one; training cannot resume from it, and a tool that needs the pool says so."""
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    torch.save({**state, **{key: None for key in TRAINING_ONLY if key in state}}, path)


def replace_dir(staging: str, target: str) -> None:
    shutil.rmtree(target, ignore_errors=True)
    os.replace(staging, target)


def carry_run(run_dir: str, carry: str) -> str:
    """Copies an unfinished run's directory to carry/<run name>/ (replacing an older copy); returns that path. The
    scripts replace their checkpoint and progress files atomically, so each copied file is whole. A run whose
    training is over (in its evaluation) is carried without replay buffer and context pool, which evaluation never
    reads: a few MB instead of tens."""
    target = os.path.join(carry, os.path.basename(os.path.normpath(run_dir)))
    staging = target + ".tmp"
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(
        run_dir, staging, ignore=lambda _, names: [n for n in names if n in NOT_CARRIED or n.endswith((".tmp", ".partial"))]
    )
    if os.path.isfile(os.path.join(staging, WEIGHTS)):
        drop_training_data_once_trained(os.path.join(staging, WEIGHTS))
    replace_dir(staging, target)
    return target


def drop_training_data_once_trained(checkpoint: str) -> None:
    """Rewrites a checkpoint written after the last training step without its replay buffer and context episodes;
    its weights, optimiser and random-number state stay, so --resume goes on with the evaluation exactly."""
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=False, mmap=True)
    total = (state.get("args") or {}).get("total_timesteps")
    if total is None or state.get("global_step", -1) < total:  # None: the family's default, unknown here: keep all
        return
    if state.get("contexts") is not None:  # (episodes per environment, episodes collected so far)
        state["contexts"] = ([[] for _ in state["contexts"][0]], state["contexts"][1])
    state["replay"] = None
    torch.save(state, checkpoint + ".partial")  # not over the file itself: the loaded tensors still map it
    os.replace(checkpoint + ".partial", checkpoint)


def restore_run(saved: str, root: str) -> bool:
    """Copies a carried or archived run directory into root where root lacks that run; whether it did."""
    target = os.path.join(root, os.path.basename(os.path.normpath(saved)))
    if os.path.exists(target) or not os.path.isfile(os.path.join(saved, "run.json")):
        return False
    shutil.copytree(saved, target + ".tmp", dirs_exist_ok=True)
    os.replace(target + ".tmp", target)
    return True


def is_archived(archive: str | None, name: str) -> bool:
    """Whether the archive holds the run, finished."""
    if not archive:
        return False
    path = os.path.join(archive, name, "run.json")
    if not os.path.isfile(path):
        return False
    try:
        return read_json(path).get("status") == "done"
    except DamagedRun as error:  # an archive is committed: restoring it beats silently retraining the run
        sys.exit(
            f"error: archived run damaged: {error}; restore it (git checkout -- {path}) or delete {os.path.dirname(path)} to rerun it"
        )


def archive_sweep(root: str, archive: str, carry: str | None = None) -> int:
    """Archives every finished run under root, printing (and with carry, carrying) the others; returns how many it archived."""
    archived = 0
    for name in sorted(os.listdir(root)):
        path = os.path.join(root, name, "run.json")
        if not os.path.isfile(path):
            continue
        try:
            status = read_json(path, RUN_KEYS)["status"]
            if status == "done":
                archive_run(os.path.join(root, name), archive)
                if carry:
                    shutil.rmtree(os.path.join(carry, name), ignore_errors=True)
                archived += 1
                continue
        except DamagedRun as damaged:
            print(f"warning: not archived: {damaged}")
            continue
        if carry:
            print(f"carried: {name} (status {status}) -> {carry_run(os.path.join(root, name), carry)}")
        else:
            print(f"not archived: {name} (status {status})")
    return archived


def slim_archive(archive: str) -> int:
    """Rewrites every checkpoint under an archive as weights only (archives written before WEIGHTS dropped the pool)."""
    slimmed = 0
    for name in sorted(os.listdir(archive)):
        path = os.path.join(archive, name, WEIGHTS)
        if os.path.isfile(path):
            save_weights(path, path + ".tmp")
            os.replace(path + ".tmp", path)
            slimmed += 1
    return slimmed


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", nargs="?", help="sweep directory, e.g. runs/sweeps/learn")
    parser.add_argument("archive", help="archive directory, e.g. results/learn/runs")
    parser.add_argument(
        "--carry",
        default=None,
        metavar="DIR",
        help="also copy each unfinished run's directory to DIR (e.g. results/learn/carry), as sweep.py --carry does",
    )
    parser.add_argument("--slim", action="store_true", help="only rewrite the archive's checkpoints as weights only")
    cli = parser.parse_args(argv)
    if cli.slim:
        if cli.root is not None or cli.carry:
            raise SystemExit("archive.py: error: --slim takes the archive directory alone")
        if not os.path.isdir(cli.archive):
            raise SystemExit(f"archive.py: error: {cli.archive!r} is not a directory")
        print(f"rewrote {slim_archive(cli.archive)} checkpoints in {cli.archive} as weights only")
        return
    if cli.root is None or not os.path.isdir(cli.root):
        raise SystemExit(f"archive.py: error: {cli.root!r} is not a directory")
    print(f"archived {archive_sweep(cli.root, cli.archive, cli.carry)} finished runs of {cli.root} in {cli.archive}")


if __name__ == "__main__":
    main()
