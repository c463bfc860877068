"""A torque-controlled Sawyer in pybullet, with nominal or perturbed joint dynamics.

The default velocity motors are switched off (VELOCITY_CONTROL with zero force),
so the arm moves only under gravity, the commanded joint torques (TORQUE_CONTROL,
held constant over one control period) and its joint dynamics:

- viscous damping via p.changeDynamics(jointDamping=...);
- Coulomb friction as pybullet's usual idiom, a velocity motor with target 0
  whose force limit is the friction torque (it resists motion up to that torque).

Nominal dynamics are the URDF's (Gazebo) values scaled down: Bullet applies joint
damping explicitly, and the URDF's 5 N m s/rad makes the light wrist (j6, about
1e-3 kg m^2) diverge at any practical step (measured: |dq6| grows to 100 rad/s
within 0.2 s at a 2.5 ms step). With damping 0.5 the wrist is stable at the 1 ms
physics step used here; friction is scaled by the same spirit to 1 N m so the wrist
(9 N m effort) keeps most of its authority.

The "real robot" of the sim-to-real study is `JointDynamics.perturbed(...)`:
link masses (and inertias) scaled by U(0.8, 1.2), damping and friction by
U(0.5, 1.5), drawn per link/joint from a seed.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, replace

import numpy as np
import pybullet as p

from envs.robot import ARM_JOINTS, LIMITS, NEUTRAL_Q, URDF_PATH, read_urdf
from envs.sim import Scene

PHYSICS_STEP = 0.001  # s; 10 physics steps per control period at 100 Hz
CONTROL_PERIOD = 0.01  # s; the IDM runs 10x faster than the STM's 0.1 s steps
DAMPING_SCALE = 0.1  # nominal damping = URDF damping x this (see module docstring)
FRICTION_SCALE = 0.2  # nominal friction = URDF friction x this
STATE_DIM = 14  # (q, dq/dt) of the 7 arm joints


def urdf_joint_dynamics() -> tuple[np.ndarray, np.ndarray]:
    """Damping and friction of the arm joints as written in the URDF."""
    root = ET.fromstring(read_urdf(URDF_PATH))
    dyn = {j.get("name"): j.find("dynamics") for j in root.iter("joint")}
    damping = np.array([float(dyn[n].get("damping", 0.0)) if dyn[n] is not None else 0.0 for n in ARM_JOINTS])
    friction = np.array([float(dyn[n].get("friction", 0.0)) if dyn[n] is not None else 0.0 for n in ARM_JOINTS])
    return damping, friction


def _floats(x) -> tuple[float, ...]:
    return tuple(round(float(v), 9) for v in x)


@dataclass(frozen=True)
class JointDynamics:
    """Per-joint physical parameters of the simulated arm (7 entries each; masses
    scale the child link of each arm joint, right_l0..right_l6)."""

    mass_scale: tuple[float, ...] = (1.0,) * 7
    damping: tuple[float, ...] = ()
    friction: tuple[float, ...] = ()

    @classmethod
    def nominal(cls) -> JointDynamics:
        damping, friction = urdf_joint_dynamics()
        return cls((1.0,) * 7, _floats(damping * DAMPING_SCALE), _floats(friction * FRICTION_SCALE))

    def perturbed(self, seed: int, mass: float = 0.2, damping: tuple[float, float] = (0.5, 1.5),
                  friction: tuple[float, float] = (0.5, 1.5)) -> JointDynamics:
        """Masses x U(1-mass, 1+mass), damping x U(*damping), friction x U(*friction)."""
        rng = np.random.default_rng(seed)
        return replace(
            self,
            mass_scale=_floats(np.asarray(self.mass_scale) * rng.uniform(1 - mass, 1 + mass, 7)),
            damping=_floats(np.asarray(self.damping) * rng.uniform(*damping, 7)),
            friction=_floats(np.asarray(self.friction) * rng.uniform(*friction, 7)),
        )

    def as_dict(self) -> dict:
        return {k: list(v) for k, v in asdict(self).items()}


class TorqueWorld:
    """A pybullet world (no table) with the arm under torque control at CONTROL_PERIOD."""

    def __init__(self, dynamics: JointDynamics | None = None, physics_step: float = PHYSICS_STEP,
                 control_period: float = CONTROL_PERIOD):
        self.dynamics = dynamics or JointDynamics.nominal()
        if len(self.dynamics.damping) != 7 or len(self.dynamics.friction) != 7 or len(self.dynamics.mass_scale) != 7:
            raise ValueError("JointDynamics needs 7 mass scales, dampings and frictions")
        self.scene = Scene(table=False, time_step=physics_step)
        self.client, self.robot = self.scene.client, self.scene.robot
        self.substeps = max(1, round(control_period / physics_step))
        self.control_period = self.substeps * physics_step
        self.effort = LIMITS.effort.astype(float)
        self._dofs = self.robot.arm + self.robot.fingers  # pybullet's inverse dynamics wants every moving joint
        self._apply_dynamics()
        self.reset(NEUTRAL_Q)

    def _apply_dynamics(self) -> None:
        c, body, d = self.client, self.robot.body, self.dynamics
        for j, ms, damp in zip(self.robot.arm, d.mass_scale, d.damping, strict=True):
            info = p.getDynamicsInfo(body, j, physicsClientId=c)
            p.changeDynamics(body, j, mass=info[0] * ms, localInertiaDiagonal=[x * ms for x in info[2]],
                             jointDamping=float(damp), physicsClientId=c)
        # friction motors on the arm (replace the default ones); fingers held open
        p.setJointMotorControlArray(body, self.robot.arm, p.VELOCITY_CONTROL, targetVelocities=[0.0] * 7,
                                    forces=[float(f) for f in d.friction], physicsClientId=c)
        self.scene.command(NEUTRAL_Q, grip=0.0)
        p.setJointMotorControlArray(body, self.robot.arm, p.VELOCITY_CONTROL, targetVelocities=[0.0] * 7,
                                    forces=[float(f) for f in d.friction], physicsClientId=c)

    def reset(self, q: np.ndarray, dq: np.ndarray | None = None) -> np.ndarray:
        """Teleport the arm to q (7,) with joint speeds dq (default 0); returns the state."""
        self.robot.reset(q)
        if dq is not None:
            for j, v, w in zip(self.robot.arm, q, dq, strict=True):
                p.resetJointState(self.robot.body, j, float(v), float(w), physicsClientId=self.client)
        return self.state()

    def state(self) -> np.ndarray:
        """(q, dq/dt) of the arm, shape (14,)."""
        st = p.getJointStates(self.robot.body, self.robot.arm, physicsClientId=self.client)
        return np.array([s[0] for s in st] + [s[1] for s in st])

    def tip(self) -> np.ndarray:
        return self.robot.link_pose(self.robot.tip)[0]

    def apply(self, tau: np.ndarray) -> np.ndarray:
        """Hold joint torques tau (7,) (clipped to the effort limits) for one control
        period; returns the applied torques."""
        tau = np.clip(np.asarray(tau, dtype=float), -self.effort, self.effort)
        forces = [float(x) for x in tau]
        for _ in range(self.substeps):
            # pybullet clears applied torques after each step: set them every step
            p.setJointMotorControlArray(self.robot.body, self.robot.arm, p.TORQUE_CONTROL, forces=forces,
                                        physicsClientId=self.client)
            p.stepSimulation(physicsClientId=self.client)
        return tau

    def rigid_body_torques(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """Torques (7,) of the rigid-body model of this world for (q, dq, ddq): gravity,
        Coriolis and inertia, without damping or friction."""
        fingers = [s[0] for s in p.getJointStates(self.robot.body, self.robot.fingers, physicsClientId=self.client)]
        tau = p.calculateInverseDynamics(self.robot.body, [float(v) for v in q] + fingers,
                                         [float(v) for v in dq] + [0.0, 0.0], [float(v) for v in ddq] + [0.0, 0.0],
                                         physicsClientId=self.client)
        return np.asarray(tau[:7])

    def close(self) -> None:
        self.scene.close()

    def __enter__(self) -> TorqueWorld:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
