"""Does a bounded context embedding keep CLAW's context encoder learning? (a diagnostic, not a method option)

On Reach, CLAW's u_con grows while staying nearly constant across contexts (norm 26 at 5k steps, 72 at 20k,
115 at 50k) and the context encoder's gradient shrinks with it; the generator's first LayerNorm is
scale-invariant, so a growing u_con could be what starves the encoder. This script trains or inspects CLAW
with u_con layer-normalised (no affine; the paper does not say whether u_con is normalised) by patching
`claw_tdmpc2.ContextEncoder.forward` in this process only; everything else is `claw_tdmpc2.py` unchanged.

    python benchmarks/context_norm_probe.py train <claw_tdmpc2.py flags>
    python benchmarks/context_norm_probe.py inspect <checkpoint> [inspect_adapters.py flags]
"""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MUJOCO_GL", "disable")

import torch.nn.functional as F  # noqa: E402

import claw_tdmpc2 as claw  # noqa: E402

plain_forward = claw.ContextEncoder.forward


def normalised_forward(self, transitions):
    u_con = plain_forward(self, transitions)
    return F.layer_norm(u_con, u_con.shape[-1:])


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in ("train", "inspect"):
        raise SystemExit("usage: context_norm_probe.py train <claw_tdmpc2.py flags> | inspect <checkpoint> [flags]")
    claw.ContextEncoder.forward = normalised_forward
    try:
        if argv[0] == "train":
            import tyro

            claw.main(tyro.cli(claw.Args, args=argv[1:]))
        else:
            from benchmarks import inspect_adapters

            inspect_adapters.main(argv[1:])
    finally:
        claw.ContextEncoder.forward = plain_forward


if __name__ == "__main__":
    main()
