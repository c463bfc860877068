"""The Sawyer robot: URDF location, joint names and limits, the neutral pose, and
loading it into a pybullet client.

All positions are expressed in the `right_arm_base_link` frame, which is also the
pybullet world frame of every scene in this project.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

URDF_PATH = Path(__file__).parent / "assets" / "sawyer" / "sawyer.urdf"

BASE_LINK = "right_arm_base_link"
HAND_LINK = "right_hand"
TIP_LINK = "right_gripper_tip"
ARM_JOINTS = tuple(f"right_j{i}" for i in range(7))
FINGER_JOINTS = ("right_gripper_l_finger_joint", "right_gripper_r_finger_joint")
FINGER_OPEN = 0.020833  # joint value of each finger when fully open (m)
NEUTRAL_Q = np.array([0.0, -1.18, 0.0, 2.18, 0.0, 0.57, 3.3161])


class URDFError(ValueError):
    """The robot description is missing or malformed."""


@dataclass(frozen=True)
class JointLimits:
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    def contains(self, q: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """True where every joint of `q` (..., 7) lies within the limits (+- tol)."""
        q = np.asarray(q)
        return np.all((q >= self.lower - tol) & (q <= self.upper + tol), axis=-1)

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)

    def sample(self, rng: np.random.Generator, n: int, margin: float = 0.0) -> np.ndarray:
        """Uniform joint configurations, `margin` rad inside each limit."""
        return rng.uniform(self.lower + margin, self.upper - margin, size=(n, len(self.lower)))


def read_urdf(path: str | Path = URDF_PATH) -> str:
    """Read and sanity-check a URDF file; raise URDFError with the reason otherwise."""
    path = Path(path)
    if not path.is_file():
        raise URDFError(f"robot description not found: {path}")
    text = path.read_text()
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise URDFError(f"robot description {path} is not valid XML: {exc}") from None
    if root.tag != "robot":
        raise URDFError(f"robot description {path} has root <{root.tag}>, expected <robot>")
    links = {link.get("name") for link in root.iter("link")}
    joints = {j.get("name") for j in root.iter("joint")}
    missing = [n for n in (BASE_LINK, HAND_LINK, TIP_LINK) if n not in links]
    missing += [n for n in ARM_JOINTS if n not in joints]
    if missing:
        raise URDFError(f"robot description {path} lacks {', '.join(missing)}")
    return text


def joint_limits(path: str | Path = URDF_PATH) -> JointLimits:
    """Arm joint limits (right_j0..right_j6) as read from the URDF."""
    root = ET.fromstring(read_urdf(path))
    by_name = {j.get("name"): j.find("limit") for j in root.iter("joint")}
    rows = [[float(by_name[n].get(k)) for k in ("lower", "upper", "velocity", "effort")] for n in ARM_JOINTS]
    lo, hi, vel, eff = (np.array(c) for c in zip(*rows, strict=True))
    return JointLimits(lo, hi, vel, eff)


LIMITS = joint_limits()


def load_in_pybullet(client_id: int, path: str | Path = URDF_PATH, base_position=(0.0, 0.0, 0.0)) -> PybulletRobot:
    """Load the Sawyer (fixed base) into a connected pybullet client."""
    import pybullet as p

    read_urdf(path)  # clear error for a missing or malformed file, before pybullet's terse one
    body = p.loadURDF(
        str(path),
        basePosition=base_position,
        useFixedBase=True,
        flags=p.URDF_USE_INERTIA_FROM_FILE,
        physicsClientId=client_id,
    )
    return PybulletRobot(client_id, body)


class PybulletRobot:
    """Joint and link indices of a loaded Sawyer, and pybullet-side kinematics."""

    def __init__(self, client_id: int, body: int):
        import pybullet as p

        self.client = client_id
        self.body = body
        joint_index, link_index = {}, {}
        for j in range(p.getNumJoints(body, physicsClientId=client_id)):
            info = p.getJointInfo(body, j, physicsClientId=client_id)
            joint_index[info[1].decode()] = j
            link_index[info[12].decode()] = j
        self.joint_index = joint_index
        self.link_index = link_index
        self.arm = [joint_index[n] for n in ARM_JOINTS]
        self.fingers = [joint_index[n] for n in FINGER_JOINTS]
        self.tip = link_index[TIP_LINK]
        self.hand = link_index[HAND_LINK]

    def reset(self, q: np.ndarray, finger: float = FINGER_OPEN) -> None:
        """Teleport the arm to `q` (7,) and the fingers to `finger`, at rest."""
        import pybullet as p

        for j, v in zip(self.arm, q, strict=True):
            p.resetJointState(self.body, j, float(v), 0.0, physicsClientId=self.client)
        for j in self.fingers:
            p.resetJointState(self.body, j, float(finger), 0.0, physicsClientId=self.client)

    def link_pose(self, link: int) -> tuple[np.ndarray, np.ndarray]:
        """World position (3,) and rotation matrix (3, 3) of a link's URDF frame."""
        import pybullet as p

        state = p.getLinkState(self.body, link, computeForwardKinematics=True, physicsClientId=self.client)
        pos = np.array(state[4])
        rot = np.array(p.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        return pos, rot

    def joint_positions(self) -> np.ndarray:
        import pybullet as p

        states = p.getJointStates(self.body, self.arm, physicsClientId=self.client)
        return np.array([s[0] for s in states])

