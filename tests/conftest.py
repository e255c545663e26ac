import os
import sys

# No display here: the default GLFW backend warns about X11 on import; no test renders.
os.environ.setdefault("MUJOCO_GL", "disable")
# Make the repo root importable (`common`, ...) when pytest is run from anywhere.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

# Tiny models: one thread is as fast, and several pytest/benchmark processes on a small machine
# would otherwise thrash each other's OpenMP threads (measured >100x slowdowns on 2 cores).
torch.set_num_threads(1)
