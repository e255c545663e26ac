"""Input checks shared by the diagnostics: a checkpoint or flag they cannot use is refused in one line naming it."""

from __future__ import annotations

import math
import os

import torch

NAMES = {
    "claw_tdmpc2.py": "CLAW",
    "dr_tdmpc2.py": "DR",
    "st_tdmpc2.py": "ST",
    "oracle_tdmpc2.py": "Oracle",
    "film_tdmpc2.py": "FiLM",
    "concat_tdmpc2.py": "Concat",
    "posthoc_tdmpc2.py": "post-hoc",
}
# what experiments/archive.py drops from an archived (weights-only) checkpoint, as a person names it
TRAINING_STATE = {"replay": "replay buffer", "contexts": "context pool"}


def described(methods) -> str:
    """("claw_tdmpc2.py", "film_tdmpc2.py") -> "checkpoint of CLAW or FiLM (claw_tdmpc2.py, film_tdmpc2.py)"."""
    names = [NAMES.get(m, m) for m in methods]
    listed = names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"
    return f"checkpoint of {listed} ({', '.join(methods)})"


def read_checkpoint(path: str, tool: str, methods, needs=()) -> dict:
    """The checkpoint at path, loaded on the CPU, or one error line: the path does not exist, the file is no torch file
    or is damaged, it is no checkpoint of the method scripts, another method wrote it than the tool reads (methods:
    script names), or it lacks the training state the tool needs (needs: keys of TRAINING_STATE, which archived
    checkpoints keep as None)."""
    if not os.path.exists(path):
        raise SystemExit(f"error: checkpoint {path} does not exist")
    if os.path.isdir(path):
        raise SystemExit(f"error: {path} is a directory; {tool} reads a checkpoint file (e.g. {path}/checkpoint.pt)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # truncated, corrupt or not a torch file: torch raises many types
        # torch's first sentence says what failed; the rest is advice on how files get corrupted
        detail = str(error).splitlines()[0].split(". ")[0] if str(error).strip() else ""
        raise SystemExit(
            f"error: cannot read checkpoint {path} (truncated, corrupt or not a torch file): {type(error).__name__}"
            + (f": {detail}" if detail else "")
        ) from None
    if not isinstance(state, dict) or not isinstance(state.get("args"), dict) or "model" not in state:
        raise SystemExit(f"error: {path} is not a checkpoint of the method scripts (no saved 'args' and 'model')")
    found = state.get("method", f"{state['args'].get('exp_name')}.py")  # older checkpoints: the run's exp_name
    if found not in methods:
        raise SystemExit(f"error: {path} is a {described([found])}; {tool} needs a {described(methods)}")
    state["method"] = found
    missing = [TRAINING_STATE[key] for key in needs if state.get(key) is None]
    if missing:
        raise SystemExit(
            f"error: {path} is weights only, as archived checkpoints are (no {' or '.join(missing)}); {tool} needs the "
            f"{' and '.join(TRAINING_STATE[key] for key in needs)}: give it the run's full checkpoint.pt from its run directory"
        )
    return state


def check_at_least(cli, minimum: dict) -> None:
    """One error line for the first flag below its minimum or not finite; minimum: {argparse dest: lowest valid value};
    a list-valued flag is checked entry by entry, an unset one (None) not at all."""
    for dest, low in minimum.items():
        value = getattr(cli, dest)
        for entry in value if isinstance(value, (list, tuple)) else [value]:
            if entry is None:
                continue
            if isinstance(entry, float) and not math.isfinite(entry):
                raise SystemExit(f"error: --{dest.replace('_', '-')} must be finite, got {entry}")
            if entry < low:
                raise SystemExit(f"error: --{dest.replace('_', '-')} must be >= {low}, got {entry}")
