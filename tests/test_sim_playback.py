"""Playback at the speed of its physics: Scene.play builds its joint targets in one go and commands the fingers
only when their target changes (BlockWorld.hold commands once), and the physics comes out bit for bit as from
the per-step command loop it replaced (kept here as the oracle). An episode's result does not depend on what ran
before it in the process (each pick-and-place episode has a fresh world), so episodes may run in any order or
process."""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest

from envs.blocks import PICK_XY, BlockWorld
from envs.robot import FINGER_OPEN, LIMITS
from envs.sim import GRIPPER_FORCE, Playback, interpolated_targets
from envs.tasks.pickplace import SETTLE_SECONDS, STEP_SECONDS, PickPlace, run_pick_place


def _command(scene, q_target, grip) -> None:
    """The per-step command as it was: the arm's targets and the fingers', every physics step."""
    r = scene.robot
    p.setJointMotorControlArray(r.body, r.arm, p.POSITION_CONTROL, targetPositions=list(map(float, q_target)),
                                forces=list(LIMITS.effort), physicsClientId=scene.client)
    target = 0.0 if grip >= 0.5 else FINGER_OPEN
    p.setJointMotorControlArray(r.body, r.fingers, p.POSITION_CONTROL, targetPositions=[target, target],
                                forces=[GRIPPER_FORCE, GRIPPER_FORCE], physicsClientId=scene.client)


def _reference_play_and_hold(world: BlockWorld, q: np.ndarray, grip: np.ndarray) -> Playback:
    """Scene.play then BlockWorld.hold as one loop that commands every physics step (the oracle)."""
    scene, substeps = world.scene, round(STEP_SECONDS / world.scene.time_step)
    scene.robot.reset(q[0], finger=0.0 if grip[0] >= 0.5 else FINGER_OPEN)
    qs, tips = [scene.robot.joint_positions()], [scene.robot.link_pose(scene.robot.tip)[0]]
    for t in range(1, len(q)):
        for k in range(1, substeps + 1):
            _command(scene, q[t - 1] + (q[t] - q[t - 1]) * (k / substeps), grip[t])
            p.stepSimulation(physicsClientId=scene.client)
        qs.append(scene.robot.joint_positions())
        tips.append(scene.robot.link_pose(scene.robot.tip)[0])
    for _ in range(round(SETTLE_SECONDS / scene.time_step)):
        _command(scene, q[-1], grip[-1])
        p.stepSimulation(physicsClientId=scene.client)
    return Playback(q=np.array(qs), tip=np.array(tips))


@pytest.fixture(scope="module")
def expert_episodes():
    """Two table-level pick-and-place episodes and the expert's (q, grip) for each: grasp, carry, release."""
    task = PickPlace()
    episodes = [ep for ep in task.episodes(12, 31) if ep.info["level"] == 0][:2]
    return [(ep, *task.expert_episode(ep)) for ep in episodes]


def test_interpolated_targets_are_the_per_step_targets_bit_for_bit():
    q = np.random.default_rng(0).normal(size=(6, 7))
    for substeps in (1, 7, 24):
        per_step = [[q[t - 1] + (q[t] - q[t - 1]) * (k / substeps) for k in range(1, substeps + 1)]
                    for t in range(1, len(q))]
        assert np.array_equal(np.array(interpolated_targets(q, substeps)), np.array(per_step))


def test_play_and_hold_move_the_world_as_the_per_step_command_loop(expert_episodes):
    ep, q, grip = expert_episodes[0]
    runs = []
    for play in (_reference_play_and_hold, None):
        world = BlockWorld()
        try:
            block = world.spawn(PICK_XY, 0)
            if play is None:
                playback = world.scene.play(q, grip, STEP_SECONDS)
                world.hold(q[-1], float(grip[-1]), SETTLE_SECONDS)
            else:
                playback = play(world, q, grip)
            pos, orn = p.getBasePositionAndOrientation(block, physicsClientId=world.client)
            runs.append((playback.q, playback.tip, np.array([*pos, *orn]), world.scene.robot.joint_positions()))
        finally:
            world.close()
    assert np.linalg.norm(runs[0][2][:2] - PICK_XY) > 0.1  # the expert carried the block away: contacts were played
    for ref, new in zip(runs[0], runs[1], strict=True):  # measured path, tip path, block pose, arm at the end
        assert np.array_equal(ref, new)


def test_an_episode_comes_out_the_same_whatever_ran_before_it(expert_episodes):
    (ep_a, q_a, grip_a), (ep_b, q_b, grip_b) = expert_episodes
    alone = run_pick_place(q_b, grip_b, np.asarray(ep_b.info["goal"]), 0)
    run_pick_place(q_a, grip_a, np.asarray(ep_a.info["goal"]), 0)
    after = run_pick_place(q_b, grip_b, np.asarray(ep_b.info["goal"]), 0)
    assert alone["success"] == 1.0
    assert repr(after) == repr(alone)
