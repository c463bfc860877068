"""The robot, the tasks and their demonstrations, in pybullet: the Sawyer (robot), its scenes and physics playback
(sim), the blocks of pick-and-place and stacking (blocks), forward kinematics (kinematics) and inverse kinematics
(ik), the demonstration datasets (datasets), 3D figures of a task (render), and for every package the figure files
(figure_files) and atomic writes (fileio). Subpackage: tasks (the task registry and one module per task)."""

import os
import sys


def _import_pybullet_quietly() -> None:
    """pybullet prints its build time on stderr (from C) when first imported, which turns the
    one-line errors of the command-line tools into two lines: import it once with fd 2 muted."""
    if "pybullet" in sys.modules:
        return
    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet  # noqa: F401
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


_import_pybullet_quietly()
