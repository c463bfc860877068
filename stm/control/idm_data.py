"""Training data for the inverse dynamics model (IDM): torque-controlled rollouts of
the Sawyer in pybullet, cached on disk by a hash of their configuration.

Exploration (documented choice; the paper does not say how its IDM data were made):
each episode starts at the neutral pose plus Gaussian offsets and follows a random
smooth joint reference, a cubic spline (zero speed at both ends) through waypoints
that random-walk around the neutral pose (step std `waypoint_std`, pull `pull`
back towards neutral) every U(waypoint_seconds) s, clipped inside the joint
limits. A computed-torque controller built on the *nominal* model (pybullet's
rigid-body inverse dynamics plus nominal damping/friction feed-forward, PD in
acceleration units) tracks it, and torque noise (std `torque_noise` x effort)
widens the visited state/action distribution. The noise is white by default: with
correlated noise (or none) a_t is nearly a_{t-1}, and the IDM learns to copy its
previous action instead of reading the desired next state, which fails in closed
loop (measured: the arm fell, 0.8 m tip RMSE, with 50 ms OU noise). The IDM learns
from what happened (hindsight): the next state it is asked to reach is the one the
torques produced.

A sample at control step t: inputs s_t, s_{t-1}, s_{t-2}, a_{t-1}, a_{t-2} and the
reached s_{t+1}; target a_t. States are (q, dq/dt) (14,), actions joint torques (7,).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from tqdm.auto import tqdm

from envs.fileio import atomic_open
from envs.robot import LIMITS, NEUTRAL_Q
from stm.control.torque_sim import CONTROL_PERIOD, PHYSICS_STEP, STATE_DIM, JointDynamics, TorqueWorld

log = logging.getLogger(__name__)

FORMAT_VERSION = 1  # bump when the file layout or the collection code changes meaning
HISTORY = 2  # H: previous states and actions fed to the IDM
FEATURE_DIM = STATE_DIM * (2 + HISTORY) + 7 * HISTORY  # 70


class CacheError(ValueError):
    """A cached dataset file is unreadable or does not match its configuration."""


@dataclass(frozen=True)
class ExplorationConfig:
    """Everything that shapes an IDM dataset (hashed for the cache)."""

    episodes: int = 40
    episode_seconds: float = 8.0
    waypoint_seconds: tuple[float, float] = (0.5, 1.5)
    start_std: float = 0.3  # rad, start = neutral + N(0, start_std)
    waypoint_std: float = 0.35  # rad, random-walk step between waypoints
    pull: float = 0.2  # fraction of the offset from neutral removed at each waypoint
    limit_margin: float = 0.2  # rad kept from every joint limit by the reference
    kp: float = 100.0  # 1/s^2, PD of the computed-torque explorer
    kd: float = 20.0  # 1/s
    torque_noise: float = 0.05  # noise std as a fraction of each joint's effort limit
    noise_time: float = 0.0  # s, OU correlation time; 0: white (independent per control step)
    seed: int = 0
    dynamics: JointDynamics = field(default_factory=JointDynamics.nominal)
    physics_step: float = PHYSICS_STEP
    control_period: float = CONTROL_PERIOD

    def __post_init__(self):
        if self.episodes < 1 or self.episode_seconds < 4 * self.control_period:
            raise ValueError(f"need episodes >= 1 and episode_seconds >= 4 control periods, got "
                             f"{self.episodes}, {self.episode_seconds}")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["dynamics"] = self.dynamics.as_dict()
        d["waypoint_seconds"] = list(self.waypoint_seconds)
        return d

    def config_hash(self) -> str:
        blob = json.dumps({"format": FORMAT_VERSION, **self.as_dict()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


@dataclass
class IDMData:
    """Episodes of torque control: states (E, N+1, 14), actions (E, N, 7)."""

    states: np.ndarray
    actions: np.ndarray
    config_hash: str = ""

    def __len__(self) -> int:
        """Number of training samples."""
        return self.actions.shape[0] * max(0, self.actions.shape[1] - HISTORY)

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Inputs (M, 70) and target torques (M, 7) over every episode."""
        s, a = self.states, self.actions
        N = a.shape[1]
        t = np.arange(HISTORY, N)
        x = idm_features(s[:, t], s[:, t - 1], s[:, t - 2], a[:, t - 1], a[:, t - 2], s[:, t + 1])
        return x.reshape(-1, FEATURE_DIM).astype(np.float32), a[:, t].reshape(-1, 7).astype(np.float32)


def idm_features(s, s1, s2, a1, a2, s_next) -> np.ndarray:
    """The IDM input: current state, the two previous states and actions, the desired
    next state; past and next states relative to the current one (the same facts,
    expressed as differences so that small motions are not drowned by the pose)."""
    return np.concatenate([s, s1 - s, s2 - s, a1, a2, s_next - s], axis=-1)


# collection ---------------------------------------------------------------------

def _reference(rng: np.random.Generator, cfg: ExplorationConfig, times: np.ndarray) -> CubicSpline:
    lo, hi = LIMITS.lower + cfg.limit_margin, LIMITS.upper - cfg.limit_margin
    knots_t, knots_q = [0.0], [np.clip(NEUTRAL_Q + cfg.start_std * rng.standard_normal(7), lo, hi)]
    while knots_t[-1] < times[-1]:
        knots_t.append(knots_t[-1] + rng.uniform(*cfg.waypoint_seconds))
        prev = knots_q[-1]
        nxt = prev - cfg.pull * (prev - NEUTRAL_Q) + cfg.waypoint_std * rng.standard_normal(7)
        knots_q.append(np.clip(nxt, lo, hi))
    return CubicSpline(np.array(knots_t), np.array(knots_q), axis=0, bc_type="clamped")


def collect_episode(world: TorqueWorld, model: TorqueWorld, cfg: ExplorationConfig,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One exploration episode in `world`, controlled with the nominal `model`."""
    n = int(round(cfg.episode_seconds / world.control_period))
    times = np.arange(n + 1) * world.control_period
    ref = _reference(rng, cfg, times)
    q_ref, dq_ref, ddq_ref = ref(times), ref(times, 1), ref(times, 2)
    damping, friction = np.asarray(model.dynamics.damping), np.asarray(model.dynamics.friction)
    sigma = cfg.torque_noise * world.effort
    decay = np.exp(-world.control_period / cfg.noise_time) if cfg.noise_time > 0 else 0.0
    noise = sigma * rng.standard_normal(7)
    s = world.reset(q_ref[0])
    states, actions = [s], []
    for k in range(n):
        q, dq = s[:7], s[7:]
        acc = ddq_ref[k] + cfg.kp * (q_ref[k] - q) + cfg.kd * (dq_ref[k] - dq)
        tau = model.rigid_body_torques(q, dq, acc) + damping * dq_ref[k] + friction * np.tanh(dq_ref[k] / 0.05)
        noise = decay * noise + np.sqrt(1 - decay**2) * sigma * rng.standard_normal(7)
        actions.append(world.apply(tau + noise))
        s = world.state()
        states.append(s)
    return np.array(states), np.array(actions)


def collect(cfg: ExplorationConfig, progress: bool | None = None) -> IDMData:
    """Run every exploration episode (deterministic per cfg.seed)."""
    rng = np.random.default_rng(cfg.seed)
    states, actions = [], []
    with TorqueWorld(cfg.dynamics, cfg.physics_step, cfg.control_period) as world, \
            TorqueWorld(JointDynamics.nominal(), cfg.physics_step, cfg.control_period) as model:
        disable = (not _is_tty()) if progress is None else not progress
        for _ in tqdm(range(cfg.episodes), desc="IDM data", disable=disable):
            s, a = collect_episode(world, model, cfg, rng)
            states.append(s)
            actions.append(a)
    data = IDMData(np.array(states), np.array(actions), cfg.config_hash())
    if not (np.isfinite(data.states).all() and np.isfinite(data.actions).all()):
        raise RuntimeError("IDM data collection produced non-finite states (unstable simulation)")
    return data


def _is_tty() -> bool:
    import sys

    return sys.stderr.isatty() and not os.environ.get("CI")


# cache --------------------------------------------------------------------------

def default_cache_dir() -> Path:
    """The project's dataset cache (envs.datasets: ACRMDN_CACHE, else ~/.cache/acrmdn) / idm."""
    from envs.datasets import default_cache_dir as datasets_cache_dir

    return datasets_cache_dir() / "idm"


def cache_path(cfg: ExplorationConfig, cache_dir: str | Path | None = None) -> Path:
    return Path(cache_dir if cache_dir is not None else default_cache_dir()) / f"idm_data_{cfg.config_hash()}.npz"


def save(data: IDMData, cfg: ExplorationConfig, path: str | Path) -> None:
    """Write atomically (temporary file, then rename): a killed run leaves no half file."""
    meta = json.dumps({"format": FORMAT_VERSION, "hash": cfg.config_hash(), "config": cfg.as_dict()})
    with atomic_open(path, "wb") as fh:
        np.savez(fh, states=data.states, actions=data.actions, meta=np.array(meta))


def load(cfg: ExplorationConfig, path: str | Path) -> IDMData:
    """Read a cached dataset; CacheError says why it cannot be used."""
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # our handle: closed on any error
            states, actions, meta = z["states"], z["actions"], json.loads(str(z["meta"]))
    except Exception as exc:  # zip, pickle, key and JSON errors all mean "unreadable"
        raise CacheError(f"unreadable ({type(exc).__name__}: {exc})") from None
    if meta.get("format") != FORMAT_VERSION or meta.get("hash") != cfg.config_hash():
        raise CacheError(f"stale (format {meta.get('format')}, hash {meta.get('hash')})")
    E = cfg.episodes
    N = int(round(cfg.episode_seconds / (max(1, round(cfg.control_period / cfg.physics_step)) * cfg.physics_step)))
    if states.shape != (E, N + 1, STATE_DIM) or actions.shape != (E, N, 7):
        raise CacheError(f"shapes {states.shape}, {actions.shape} do not match the configuration")
    if not (np.isfinite(states).all() and np.isfinite(actions).all()):
        raise CacheError("non-finite values")
    return IDMData(states, actions, cfg.config_hash())


def load_or_collect(cfg: ExplorationConfig, cache_dir: str | Path | None = None,
                    progress: bool | None = None) -> IDMData:
    """The dataset for cfg: from the cache when valid; a corrupt or stale file gets one
    warning and is rebuilt."""
    path = cache_path(cfg, cache_dir)
    if path.exists():
        try:
            data = load(cfg, path)
            log.info("IDM data %s from cache %s (%d samples)", data.config_hash, path, len(data))
            return data
        except CacheError as exc:
            warnings.warn(f"IDM data cache {path} is {exc}; rebuilding it", RuntimeWarning, stacklevel=2)
    log.info("collecting IDM data %s (%d episodes of %.1f s)", cfg.config_hash(), cfg.episodes, cfg.episode_seconds)
    data = collect(cfg, progress)
    save(data, cfg, path)
    return data
