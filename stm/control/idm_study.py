"""The IDM study: train the IDM in simulation, track reacher plans with it at 10x the
STM's rate, and repeat on a "real" robot with perturbed dynamics, before and after
fine-tuning on data from that robot.

Metrics per condition (prefix/metric), means over the plans:
  tip_rmse_vs_plan_m      RMS tip distance to the plan's forward kinematics, at the plan's steps
  tip_rmse_vs_position_m  ... to the tip measured when the plan is played in position control
  joint_rmse_rad          RMS joint error to the planned spline at the control rate
  max_tip_error_m         largest tip distance to the plan's forward kinematics
  final_error_m           tip distance to the goal at the end of the plan
  success_rate            fraction with final_error_m < 5 cm (the reacher's criterion)
Conditions: position (position-control playback, envs.sim.Scene.play, nominal
robot), sim (sim IDM on the nominal robot), real_sim_idm (sim IDM on the perturbed
robot), real_finetuned (sim IDM fine-tuned on perturbed-robot data), real_scratch
(trained on the perturbed-robot data alone, the same data as the fine-tuning).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, field, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
from pydantic import Field, ValidationInfo, field_validator
from pydantic.dataclasses import dataclass as pydantic_dataclass

from envs.figure_files import save_figure
from envs.kinematics import tip_position_np
from envs.sim import Scene
from envs.tasks.reacher import SUCCESS_RADIUS  # the reacher's success criterion
from stm.config import STRICT, NonNegativeFloat, NonNegativeInt, PositiveFloat, PositiveInt
from stm.control.idm import (
    FastIDM,
    IDMConfig,
    IDMController,
    InverseDynamicsMDN,
    Tracking,
    save_idm,
    track_plan,
    train_idm,
)
from stm.control.idm_data import ExplorationConfig, idm_features, load_or_collect
from stm.control.smoothing import smooth_gd
from stm.control.torque_sim import TorqueWorld

log = logging.getLogger(__name__)

@pydantic_dataclass(frozen=True, config=STRICT)
class ExplorationSettings(ExplorationConfig):
    """An ExplorationConfig whose field types are checked (the study's dataset comes from a profile)."""


FloatRange = tuple[NonNegativeFloat, NonNegativeFloat]


@pydantic_dataclass(frozen=True, config=STRICT)
class IDMStudyConfig:
    data: ExplorationConfig = field(default_factory=ExplorationSettings)
    idm: IDMConfig = field(default_factory=IDMConfig)
    real_seed: int = 1  # draw of the perturbed "real" dynamics
    real_mass: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.2  # link masses (and inertias) x U(1 - m, 1 + m)
    real_damping: FloatRange = (0.5, 1.5)  # joint damping x U(range)
    real_friction: FloatRange = (0.5, 1.5)  # joint friction x U(range)
    real_episodes: PositiveInt = 10  # episodes of fine-tuning data collected on the perturbed robot
    finetune_epochs: NonNegativeInt = 20
    finetune_lr: PositiveFloat = 3e-4
    scratch_baseline: bool = True  # also train on the perturbed data alone
    plan_steps: Annotated[int, Field(ge=2)] = 60
    smoothing_gamma: NonNegativeFloat = 0.0  # > 0: smooth the plans first (stm.control.smoothing, the paper's pipeline)
    smoothing_goal_weight: NonNegativeFloat = 0.0  # goal term of that smoothing (needs goals)
    step_seconds: PositiveFloat = 0.1  # the STM's step; the IDM runs at data.control_period
    torch_threads: PositiveInt = 1  # small matmuls: extra threads only add contention on a shared CPU

    @field_validator("real_damping", "real_friction")
    @classmethod
    def _range(cls, lo_hi: tuple[float, float]) -> tuple[float, float]:
        if lo_hi[0] > lo_hi[1]:
            raise ValueError(f"{list(lo_hi)!r} is not allowed; allowed: [low, high] with 0 <= low <= high")
        return lo_hi

    @field_validator("step_seconds")
    @classmethod
    def _step(cls, step: float, info: ValidationInfo) -> float:
        data = info.data.get("data")
        if data is not None and step < data.control_period:
            raise ValueError(f"{step!r} is not allowed; allowed: >= data.control_period ({data.control_period})")
        return step

    def params(self) -> dict:
        """Flat parameters for tracking (MLflow)."""
        out = {f"data.{k}": v for k, v in self.data.as_dict().items() if k != "dynamics"}
        out.update({f"idm.{k}": v for k, v in asdict(self.idm).items()})
        out.update({k: v for k, v in asdict(self).items() if k not in ("data", "idm")})
        return out


def position_playback_tips(plans: np.ndarray, step_seconds: float) -> np.ndarray:
    """Tips (B, T+1, 3) of the plans played in position control (no table)."""
    with Scene(table=False) as scene:
        return np.stack([scene.play(plan, None, step_seconds).tip for plan in plans])


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def tracking_metrics(tr: Tracking, plan: np.ndarray, goal: np.ndarray, position_tip: np.ndarray) -> dict[str, float]:
    tip = tr.tip[:: tr.ratio]  # at the plan's steps
    plan_tip = tip_position_np(plan)
    final = float(np.linalg.norm(tip[-1] - goal))
    return {
        "tip_rmse_vs_plan_m": _rms(np.linalg.norm(tip - plan_tip, axis=-1)),
        "tip_rmse_vs_position_m": _rms(np.linalg.norm(tip - position_tip, axis=-1)),
        "joint_rmse_rad": _rms(tr.q - tr.q_desired),
        "max_tip_error_m": float(np.linalg.norm(tip - plan_tip, axis=-1).max()),
        "final_error_m": final,
        "success_rate": float(final < SUCCESS_RADIUS),
    }


def position_metrics(position_tip: np.ndarray, plan: np.ndarray, goal: np.ndarray) -> dict[str, float]:
    """The position-control reference, measured like the IDM (at the plan's steps)."""
    plan_tip = tip_position_np(plan)
    final = float(np.linalg.norm(position_tip[-1] - goal))
    return {"tip_rmse_vs_plan_m": _rms(np.linalg.norm(position_tip - plan_tip, axis=-1)),
            "max_tip_error_m": float(np.linalg.norm(position_tip - plan_tip, axis=-1).max()),
            "final_error_m": final, "success_rate": float(final < SUCCESS_RADIUS)}


def _mean_rows(rows: list[dict[str, float]]) -> dict[str, float]:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def evaluate_idm(world: TorqueWorld, model: InverseDynamicsMDN, plans: np.ndarray, goals: np.ndarray,
                 position_tips: np.ndarray, step_seconds: float) -> tuple[dict[str, float], list[Tracking]]:
    """Track every plan in `world`; metrics averaged over plans, and the trackings."""
    policy = FastIDM(model)
    rows, trackings = [], []
    for plan, goal, pos_tip in zip(plans, goals, position_tips, strict=True):
        tr = track_plan(world, policy, plan, step_seconds)
        trackings.append(tr)
        rows.append(tracking_metrics(tr, plan, goal, pos_tip))
    out = _mean_rows(rows)
    out["control_step_ms"] = 1e3 * float(np.mean([t.step_time_s for t in trackings]))
    return out, trackings


def measure_latency(model: InverseDynamicsMDN, repeats: int = 2000) -> dict[str, float]:
    """Median wall time (ms) of one control step at batch 1: features + numpy network
    (the control loop's path), and the torch module under inference_mode."""
    rng = np.random.default_rng(0)
    s = 0.01 * rng.standard_normal(14)
    ctrl = IDMController(FastIDM(model))
    ctrl.reset(s)
    fast = []
    for _ in range(repeats):
        start = time.perf_counter()
        ctrl(s, s)
        fast.append(time.perf_counter() - start)
    x = torch.as_tensor(idm_features(s, s, s, np.zeros(7), np.zeros(7), s), dtype=torch.float32)[None]
    slow = []
    with torch.inference_mode():
        for _ in range(max(1, repeats // 4)):
            start = time.perf_counter()
            model.torques(x)
            slow.append(time.perf_counter() - start)
    return {"latency_fast_ms": 1e3 * float(np.median(fast)), "latency_torch_ms": 1e3 * float(np.median(slow))}


def idm_study(cfg: IDMStudyConfig | None = None, plans: np.ndarray | None = None, goals: np.ndarray | None = None,
              cache_dir: str | Path | None = None, out_dir: str | Path | None = None,
              progress: bool | None = None, sim_model: InverseDynamicsMDN | None = None) -> dict:
    """Run the study; returns a flat metrics dict ('<condition>/<metric>', data hashes,
    NLLs, timings, latency). Plans (B, T+1, 7) and goals (B, 3) default to the reacher
    expert's plans to the four goals. `sim_model`: an IDM already trained in
    simulation (skips data and training). With `out_dir`: the tracking figure
    (PNG + PDF) and the two IDM checkpoints, listed under 'figures' and 'artifacts'."""
    cfg = cfg or IDMStudyConfig()
    from stm.control.plans import FOUR_GOALS, straight_line_plans

    threads = torch.get_num_threads()
    torch.set_num_threads(cfg.torch_threads)
    try:
        if plans is None:
            goals = FOUR_GOALS if goals is None else np.asarray(goals, dtype=float)
            plans = straight_line_plans(goals, steps=cfg.plan_steps)
        elif goals is None:
            raise ValueError("idm_study: plans given without their goals")
        plans, goals = np.asarray(plans, dtype=float), np.asarray(goals, dtype=float).reshape(-1, 3)
        if len(plans) != len(goals):
            raise ValueError(f"idm_study: {len(plans)} plans but {len(goals)} goals")
        res: dict = {}
        if cfg.smoothing_gamma > 0:
            plans = smooth_gd(plans, cfg.smoothing_gamma, goal=goals, goal_weight=cfg.smoothing_goal_weight)
        position_tips = position_playback_tips(plans, cfg.step_seconds)
        rows = [position_metrics(pt, plan, g) for pt, plan, g in zip(position_tips, plans, goals, strict=True)]
        res.update({f"position/{k}": v for k, v in _mean_rows(rows).items()})

        if sim_model is None:
            t0 = time.perf_counter()
            data = load_or_collect(cfg.data, cache_dir, progress)
            t1 = time.perf_counter()
            sim_model, hist = train_idm(data, cfg.idm, progress=progress)
            t2 = time.perf_counter()
            res.update({"data_hash": data.config_hash, "data_samples": len(data), "data_seconds": t1 - t0,
                        "train_seconds": t2 - t1, "train_nll": hist["train_nll"][-1],
                        "val_nll": hist["val_nll"][-1] if hist["val_nll"] else float("nan")})

        nominal = cfg.data.dynamics
        real_dyn = nominal.perturbed(cfg.real_seed, cfg.real_mass, cfg.real_damping, cfg.real_friction)
        res["real_dynamics"] = real_dyn.as_dict()
        trackings: dict[str, list[Tracking]] = {}
        with TorqueWorld(nominal, cfg.data.physics_step, cfg.data.control_period) as world:
            m, trackings["sim"] = evaluate_idm(world, sim_model, plans, goals, position_tips, cfg.step_seconds)
        res.update({f"sim/{k}": v for k, v in m.items()})

        real_cfg = replace(cfg.data, dynamics=real_dyn, episodes=cfg.real_episodes, seed=cfg.data.seed + 1000)
        real_data = load_or_collect(real_cfg, cache_dir, progress)
        res.update({"real_data_hash": real_data.config_hash, "real_data_samples": len(real_data)})
        ft_model = InverseDynamicsMDN(sim_model.cfg)
        ft_model.load_state_dict(sim_model.state_dict())
        ft_cfg = replace(sim_model.cfg, epochs=cfg.finetune_epochs, lr=cfg.finetune_lr, seed=cfg.idm.seed)
        ft_model, ft_hist = train_idm(real_data, ft_cfg, model=ft_model, progress=progress)
        res["finetune_val_nll"] = ft_hist["val_nll"][-1] if ft_hist["val_nll"] else float("nan")
        models = {"real_sim_idm": sim_model, "real_finetuned": ft_model}
        if cfg.scratch_baseline:
            models["real_scratch"], _ = train_idm(real_data, cfg.idm, progress=progress)
        with TorqueWorld(real_dyn, cfg.data.physics_step, cfg.data.control_period) as world:
            for name, model in models.items():
                m, trackings[name] = evaluate_idm(world, model, plans, goals, position_tips, cfg.step_seconds)
                res.update({f"{name}/{k}": v for k, v in m.items()})
        res.update(measure_latency(sim_model))

        if out_dir is not None:
            out = Path(out_dir)
            out.mkdir(parents=True, exist_ok=True)
            res["figures"] = plot_tracking(trackings, plans, position_tips, cfg.step_seconds, out / "idm_tracking")
            res["artifacts"] = [str(out / "idm_sim.pt"), str(out / "idm_finetuned.pt")]
            save_idm(sim_model, res["artifacts"][0])
            save_idm(ft_model, res["artifacts"][1])
        return res
    finally:
        torch.set_num_threads(threads)


def plot_tracking(trackings: dict[str, list[Tracking]], plans: np.ndarray, position_tips: np.ndarray,
                  step_seconds: float, path_stem: str | Path, index: int = 0) -> list[str]:
    """The paper's tracking plot for plan `index`: tip x, y, z over time, plan vs
    position control vs each IDM condition. Writes <path_stem>.png/.pdf."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(trackings.values()))[index]
    plan_tip = tip_position_np(first.q_desired)
    t_plan = np.arange(len(plans[index])) * step_seconds
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.6), sharex=True)
    labels = {"sim": "IDM, sim robot", "real_sim_idm": "IDM (sim-trained), real robot",
              "real_finetuned": "IDM (fine-tuned), real robot", "real_scratch": "IDM (real data only), real robot"}
    for d, ax in enumerate(axes[:3]):
        ax.plot(first.times, plan_tip[:, d], "k--", lw=1.5, label="plan")
        ax.plot(t_plan, position_tips[index][:, d], "o", color="0.5", ms=3, label="position control")
        for i, (name, trs) in enumerate(trackings.items()):
            ax.plot(trs[index].times, trs[index].tip[:, d], color=f"C{i}", lw=1.2, label=labels.get(name, name))
        lo, hi = plan_tip[:, d].min(), plan_tip[:, d].max()
        pad = max(0.03, 0.2 * (hi - lo))
        ax.set_ylim(lo - pad, hi + pad)  # a diverging run leaves the frame instead of flattening the rest
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"tip {'xyz'[d]} [m]")
    ax = axes[3]  # the differences are mm on a 30 cm motion: show the error itself
    plan_tip_coarse = tip_position_np(plans[index])
    ax.plot(t_plan, 1e3 * np.linalg.norm(position_tips[index] - plan_tip_coarse, axis=-1), "o", color="0.5", ms=3)
    for i, trs in enumerate(trackings.values()):
        ax.plot(trs[index].times, 1e3 * np.linalg.norm(trs[index].tip - plan_tip, axis=-1), color=f"C{i}", lw=1.2)
    ax.set_xlabel("time [s]")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_ylabel("tip error to plan [mm]")
    axes[0].legend(fontsize=7)
    fig.suptitle("Tool-tip tracking: plan vs IDM torque control")
    fig.tight_layout()
    return save_figure(fig, path_stem)
