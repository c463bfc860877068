"""Block scenes for pick-and-place and stacking: the block, the grasp-friendly
contact parameters of the gripper, spawning blocks and checking where they rest.

Facts and choices (all positions in the base frame, metres):
- Blocks are 4 cm cubes of 50 g (the open gripper leaves 4.85 mm on each side
  of a block; closed on a block, each 40 N finger pushes through friction 1.5).
- Contact parameters: block and table lateral friction 1.0, finger pads 1.5 (pybullet
  multiplies the two: 1.5 between a pad and a block). Block restitution is 0, so a
  released block settles at once. Blocks use pybullet's friction anchors: without them
  a squeezed block creeps (1-3 mm per carry) through the soft contacts; with them it
  stays put in the hand (< 0.1 mm). Spinning/rolling friction is left at 0: with the
  anchors it changed nothing measurable and made the physics about 1.5x slower.
- The two fingers are coupled by a gear constraint (ratio -1), like the real gripper's
  mechanism (the URDF's <mimic>, which pybullet ignores): without it, two independent
  force-limited finger motors squeezing a block let the solver push it against one pad,
  5 mm off centre and creeping during the carry.
- Blocks always appear at PICK_XY, resting on the table, faces aligned with the
  base axes (the expert grasps with the fingers closing along the base x axis).
- A level-L position is the bottom face of the L-th block of a tower: its z is
  TABLE_TOP_Z + L * BLOCK_SIZE (the psi/goal convention of the pick-place tasks).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as p

from envs.sim import TABLE_TOP_Z, Scene, finger_target

BLOCK_SIZE = 0.04  # edge of the cube (m)
BLOCK_MASS = 0.05  # kg
BLOCK_FRICTION = 1.0
FINGER_FRICTION = 1.5
FINGER_COUPLING_FORCE = 2000.0  # N, max force of the finger gear constraint
FINGER_COUPLING_ERP = 0.5
PICK_XY = (0.55, -0.20)  # where every block appears
BLOCK_RGBA = ((0.85, 0.25, 0.2, 1.0), (0.2, 0.6, 0.85, 1.0), (0.95, 0.8, 0.2, 1.0))


def level_z(level: float) -> float:
    """Height of the bottom face of a block at tower level `level` (0 = on the table)."""
    return TABLE_TOP_Z + level * BLOCK_SIZE


@dataclass(frozen=True)
class BlockState:
    """Where a block rests: centre position (3,) and how far it is tilted (rad)."""

    centre: np.ndarray
    tilt: float

    @property
    def bottom(self) -> np.ndarray:
        """Centre of the block's bottom face (for an upright block)."""
        return self.centre - np.array([0.0, 0.0, BLOCK_SIZE / 2])


class BlockWorld:
    """A Scene with grasp-tuned, coupled fingers and any number of blocks. The tasks
    build a fresh one per episode (about 10 ms: 1-3 % of its physics) so that results do not depend on what
    ran before in the same pybullet world; clear() removes the blocks."""

    def __init__(self, scene: Scene | None = None):
        self.scene = scene or Scene(table=True)
        self.client = self.scene.client
        self.blocks: list[int] = []
        robot = self.scene.robot
        for link in robot.fingers:  # in pybullet a fixed/prismatic joint's index is its child link's
            p.changeDynamics(robot.body, link, lateralFriction=FINGER_FRICTION, physicsClientId=self.client)
        self.coupling = couple_fingers(self.scene)
        if self.scene.table is not None:
            p.changeDynamics(self.scene.table, -1, lateralFriction=BLOCK_FRICTION, physicsClientId=self.client)

    def spawn(self, xy, level: int = 0) -> int:
        """A block resting with its bottom at tower level `level` above xy."""
        h = BLOCK_SIZE / 2
        rgba = BLOCK_RGBA[len(self.blocks) % len(BLOCK_RGBA)]
        body = self.scene.add_box((h, h, h), (float(xy[0]), float(xy[1]), level_z(level) + h),
                                  mass=BLOCK_MASS, rgba=rgba, lateral_friction=BLOCK_FRICTION)
        p.changeDynamics(body, -1, restitution=0.0, frictionAnchor=1, physicsClientId=self.client)
        self.blocks.append(body)
        return body

    def spawn_pick_block(self) -> int | None:
        """A new block at the pick position, unless one still occupies it (then None)."""
        for body in self.blocks:
            c = self.state(body).centre
            if np.hypot(c[0] - PICK_XY[0], c[1] - PICK_XY[1]) < BLOCK_SIZE * 1.5 and c[2] < level_z(1) + 0.01:
                return None
        return self.spawn(PICK_XY, 0)

    def clear(self) -> None:
        for body in self.blocks:
            self.scene.remove(body)
        self.blocks = []

    def state(self, body: int) -> BlockState:
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        # a cube stands upright when any of its axes points up: the world-z row of its rotation
        axes = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
        tilt = float(np.arccos(np.clip(np.abs(axes[2]).max(), -1.0, 1.0)))
        return BlockState(centre=np.array(pos), tilt=tilt)

    def robot_touches(self, body: int) -> bool:
        return len(p.getContactPoints(self.scene.robot.body, body, physicsClientId=self.client)) > 0

    def tip_position(self) -> np.ndarray:
        return self.scene.robot.link_pose(self.scene.robot.tip)[0]

    def hold(self, q: np.ndarray, grip: float, seconds: float) -> None:
        """Hold the targets q (7,) and grip while the world settles for `seconds` (commanded once: a motor keeps
        its target, as Scene.play relies on)."""
        n = max(1, round(seconds / self.scene.time_step))
        targets, finger = list(map(float, q)), finger_target(grip)
        self.scene.command_arm(targets)
        self.scene.command_fingers(finger)
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.client)

    def close(self) -> None:
        self.scene.close()


def couple_fingers(scene: Scene) -> int:
    """Make the fingers mirror each other (gear ratio -1 between their joints); returns the constraint id."""
    robot = scene.robot
    c = p.createConstraint(robot.body, robot.fingers[0], robot.body, robot.fingers[1], jointType=p.JOINT_GEAR,
                           jointAxis=[0, 1, 0], parentFramePosition=[0, 0, 0], childFramePosition=[0, 0, 0],
                           physicsClientId=scene.client)
    p.changeConstraint(c, gearRatio=-1, erp=FINGER_COUPLING_ERP, maxForce=FINGER_COUPLING_FORCE,
                       physicsClientId=scene.client)
    return c


def rests_at(state: BlockState, goal: np.ndarray, xy_tol: float = 0.02, z_tol: float = 0.01,
             max_tilt: float = 0.2) -> bool:
    """Whether an upright block rests with its bottom face at `goal` (xy within xy_tol, z within z_tol)."""
    bottom = state.bottom
    return bool(np.hypot(*(bottom[:2] - goal[:2])) <= xy_tol and abs(bottom[2] - goal[2]) <= z_tol
                and state.tilt <= max_tilt)
