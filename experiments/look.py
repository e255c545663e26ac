"""The five-minute look: the whole pipeline once, end to end, at a size that finishes in minutes on a 2-core CPU.

    python experiments/look.py                 # runs/look/: 8 tiny runs, summary.md, claims.md, exp1.png, exp2.png

A tiny Exp 1/2 sweep on Reach (CLAW, DR, ST, Oracle; 2 seeds; model size I, 800 agent steps, a one-iteration planner;
the "look" scale of experiments/sweep.py) through the local launcher with two workers, then experiments/aggregate.py
(tables with 95% intervals and the claims at n = 2) and experiments/figures.py. Nothing here learns the task: the
numbers show the format of a result, not a result (RESULTS.md has those). Rerunning it skips what is done; --root
elsewhere starts anew.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from experiments import aggregate, figures, sweep  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default=os.path.join("runs", "look"), help="sweep directory (default runs/look)")
    parser.add_argument("--workers", type=int, default=2, help="runs at once, one thread each (default 2)")
    cli = parser.parse_args(argv)
    if cli.workers < 1:
        raise SystemExit(f"error: --workers must be >= 1, got {cli.workers}")
    started = time.time()
    methods = ["claw", "dr", "st", "oracle"]
    launch = ["exp1", "exp2", "--scale", "look", "--launcher", "local", "--workers", str(cli.workers), "--root", cli.root]
    sweep.main([*launch, "--methods", *methods])  # exits with a line naming the failed runs, if any
    aggregate.main([cli.root])
    figures.main([cli.root])
    print(f"\nlook done in {time.time() - started:.0f} s. Open:")
    for name in ("summary.md", "claims.md", "exp1.png", "exp2.png"):
        print(f"  {os.path.join(cli.root, name)}")


if __name__ == "__main__":
    main()
