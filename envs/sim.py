"""pybullet scenes: the Sawyer on its pedestal, a table in front, and playback of
joint-position trajectories in real physics (position control, gripper, contacts).

The world frame is the robot's `right_arm_base_link` frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as p

from envs.robot import FINGER_OPEN, LIMITS, NEUTRAL_Q, PybulletRobot, load_in_pybullet

TIME_STEP = 1.0 / 240.0
TABLE_TOP_Z = -0.15  # table surface height in the base frame (m)
TABLE_CENTER_XY = (0.65, 0.0)
TABLE_HALF_EXTENTS = (0.35, 0.6, 0.02)
GRIPPER_FORCE = 40.0  # N per finger when closing


@dataclass
class Playback:
    """What a trajectory did in physics."""

    q: np.ndarray  # (T+1, 7) measured joint positions at the end of each step
    tip: np.ndarray  # (T+1, 3) measured tool-tip positions


def finger_target(grip: float) -> float:
    """The fingers' joint target for a grip command in [0, 1]: closed (0) from 0.5 on, else open."""
    return 0.0 if grip >= 0.5 else FINGER_OPEN


def interpolated_targets(q: np.ndarray, substeps: int) -> list[list[list[float]]]:
    """The arm's joint targets that play commands between the rows of q (T+1, 7): per row t >= 1, for substep
    k = 1..substeps, q[t-1] + (q[t] - q[t-1]) * (k / substeps), as nested lists (the floats pybullet takes, built
    in one go rather than per physics step; the same floats as per step)."""
    frac = np.array([k / substeps for k in range(1, substeps + 1)])
    return (q[:-1, None, :] + (q[1:] - q[:-1])[:, None, :] * frac[None, :, None]).tolist()


class Scene:
    """A pybullet world in DIRECT mode (or GUI) with the robot and, optionally, the table."""

    def __init__(self, table: bool = True, gui: bool = False, time_step: float = TIME_STEP):
        self.client = p.connect(p.GUI if gui else p.DIRECT)
        self.time_step = time_step
        p.setGravity(0, 0, -9.81, physicsClientId=self.client)
        p.setTimeStep(time_step, physicsClientId=self.client)
        self.robot: PybulletRobot = load_in_pybullet(self.client)
        self._arm_forces = [float(f) for f in LIMITS.effort]
        self.table = self._add_table() if table else None
        self.robot.reset(NEUTRAL_Q)

    # scene building --------------------------------------------------------
    def add_box(self, half_extents, position, mass: float = 0.0, rgba=(0.6, 0.6, 0.6, 1), lateral_friction=1.0) -> int:
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half_extents, physicsClientId=self.client)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half_extents, rgbaColor=rgba, physicsClientId=self.client)
        body = p.createMultiBody(mass, col, vis, basePosition=position, physicsClientId=self.client)
        p.changeDynamics(body, -1, lateralFriction=lateral_friction, physicsClientId=self.client)
        return body

    def _add_table(self) -> int:
        x, y = TABLE_CENTER_XY
        hz = TABLE_HALF_EXTENTS[2]
        return self.add_box(TABLE_HALF_EXTENTS, (x, y, TABLE_TOP_Z - hz), rgba=(0.55, 0.4, 0.25, 1))

    def body_position(self, body: int) -> np.ndarray:
        return np.array(p.getBasePositionAndOrientation(body, physicsClientId=self.client)[0])

    def remove(self, body: int) -> None:
        p.removeBody(body, physicsClientId=self.client)

    # control -----------------------------------------------------------------
    def command(self, q_target: np.ndarray, grip: float | None = None) -> None:
        """Joint-position targets for the arm; grip in [0, 1] (>= 0.5 closes the fingers)."""
        self.command_arm(list(map(float, q_target)))
        if grip is not None:
            self.command_fingers(finger_target(grip))

    def command_arm(self, targets: list[float]) -> None:
        """Joint-position targets (7 floats) for the arm, at the URDF's effort limits."""
        p.setJointMotorControlArray(self.robot.body, self.robot.arm, p.POSITION_CONTROL, targetPositions=targets,
                                    forces=self._arm_forces, physicsClientId=self.client)

    def command_fingers(self, target: float) -> None:
        """One position target for both fingers, at GRIPPER_FORCE each."""
        p.setJointMotorControlArray(self.robot.body, self.robot.fingers, p.POSITION_CONTROL,
                                    targetPositions=[target, target], forces=[GRIPPER_FORCE, GRIPPER_FORCE],
                                    physicsClientId=self.client)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.client)

    def play(self, q: np.ndarray, grip: np.ndarray | None = None, step_seconds: float = 0.1,
             on_step=None) -> Playback:
        """Run a joint-position trajectory q (T+1, 7) from its first row, one row per
        `step_seconds`, targets interpolated linearly between rows. `on_step(t)` is
        called after step t (e.g. to swap blocks). Returns the measured path.
        The arm gets its target every physics step, the fingers theirs when it changes: a motor
        keeps its target, so the physics is bit for bit that of commanding both every step
        (tests/test_sim_playback.py), without the Python around the steps."""
        q = np.asarray(q, dtype=float)
        fingers = None if grip is None else [finger_target(g) for g in np.asarray(grip, dtype=float)]
        substeps = max(1, round(step_seconds / self.time_step))
        targets = interpolated_targets(q, substeps)
        self.robot.reset(q[0], finger=FINGER_OPEN if fingers is None else fingers[0])
        qs, tips = [self.robot.joint_positions()], [self.robot.link_pose(self.robot.tip)[0]]
        finger = None  # the fingers' last commanded target
        for t in range(1, len(q)):
            for row in targets[t - 1]:
                self.command_arm(row)
                if fingers is not None and fingers[t] != finger:
                    finger = fingers[t]
                    self.command_fingers(finger)
                p.stepSimulation(physicsClientId=self.client)
            qs.append(self.robot.joint_positions())
            tips.append(self.robot.link_pose(self.robot.tip)[0])
            if on_step is not None:
                on_step(t)
        return Playback(q=np.array(qs), tip=np.array(tips))

    def close(self) -> None:
        if self.client is not None and p.isConnected(self.client):
            p.disconnect(self.client)
        self.client = None

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
