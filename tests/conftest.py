import os
import sys

# No display here: the default GLFW backend warns about X11 on import; no test renders.
os.environ.setdefault("MUJOCO_GL", "disable")
# Make the repo root importable (`common`, ...) when pytest is run from anywhere.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
