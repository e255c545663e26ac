"""What a finished sweep run measured, kept without its checkpoint in a directory small enough to commit.

A sweep directory lives on one machine, beside multi-megabyte checkpoints. When the machine is lost, so is every
finished run's measurement (this happened between the ninth and tenth sessions: 23 finished runs gone, only their
aggregated tables left, no per-seed values to pool with new seeds). An archived run is its run.json, its
TensorBoard scalars as JSON (scalars.json), its stdout.log, for an in-context method's run context_effect.md
(`context_effect.py`: how much the context moves the world model's predictions, measured on the checkpoint), for a
CLAW run inspect_adapters.txt (`inspect_adapters.py`: do u_con and the adapters tell the environments apart) and,
for the context controls, controls.json and controls.md: ~100-200 kB for a 50,000-step run. `aggregate.py` and `figures.py` read an archive like a sweep directory, and
`experiments.py --archive DIR` archives each run as it finishes and skips the runs the archive holds.

    python benchmarks/archive.py /work/sweeps/learn results/learn/runs   # archive every finished run of a sweep
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import shutil

SCALARS = "scalars.json"
KEPT = ("stdout.log", "context_effect.md", "inspect_adapters.txt", "controls.json", "controls.md")  # copied as they are, where the run wrote them


def read_scalars(run_dir: str) -> tuple[dict, list]:
    """({tag: [(step, value), ...]} sorted by step, [tags that repeat a step]) from an archived run's scalars.json,
    else from the run's TensorBoard events (where a step repeats, the last value wins, as in TensorBoard)."""
    path = os.path.join(run_dir, SCALARS)
    if os.path.isfile(path):
        with open(path) as f:
            archived = json.load(f)
        return {tag: [tuple(point) for point in points] for tag, points in archived["scalars"].items()}, archived["duplicated"]
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
    shutil.rmtree(staging, ignore_errors=True)
    os.makedirs(staging)
    scalars, duplicated = read_scalars(run_dir)
    with open(os.path.join(staging, SCALARS), "w") as f:
        json.dump({"scalars": scalars, "duplicated": duplicated}, f, separators=(",", ":"))
    for name in KEPT:
        if os.path.isfile(os.path.join(run_dir, name)):
            shutil.copy2(os.path.join(run_dir, name), staging)
    shutil.copy2(os.path.join(run_dir, "run.json"), staging)  # last: a copy with run.json is complete
    shutil.rmtree(target, ignore_errors=True)
    os.replace(staging, target)
    return target


def is_archived(archive: str | None, name: str) -> bool:
    """Whether the archive holds the run, finished."""
    if not archive:
        return False
    path = os.path.join(archive, name, "run.json")
    if not os.path.isfile(path):
        return False
    with open(path) as f:
        return json.load(f).get("status") == "done"


def archive_sweep(root: str, archive: str) -> int:
    """Archives every finished run under root, printing the others; returns how many it archived."""
    archived = 0
    for name in sorted(os.listdir(root)):
        path = os.path.join(root, name, "run.json")
        if not os.path.isfile(path):
            continue
        with open(path) as f:
            status = json.load(f).get("status")
        if status == "done":
            archive_run(os.path.join(root, name), archive)
            archived += 1
        else:
            print(f"not archived: {name} (status {status})")
    return archived


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", help="sweep directory, e.g. /work/sweeps/learn")
    parser.add_argument("archive", help="archive directory, e.g. results/learn/runs")
    cli = parser.parse_args(argv)
    if not os.path.isdir(cli.root):
        raise SystemExit(f"archive.py: error: {cli.root!r} is not a directory")
    print(f"archived {archive_sweep(cli.root, cli.archive)} finished runs of {cli.root} in {cli.archive}")


if __name__ == "__main__":
    main()
