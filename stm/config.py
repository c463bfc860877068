"""Model and training configuration: two frozen dataclasses, plain data.

Every number that shapes a trained model lives here, so that it can be logged,
hashed, swept and stored in a checkpoint (`to_dict` / `from_dict`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, TypeVar

C = TypeVar("C", bound="_Config")

HEADS = ("mdn", "deterministic")
FEEDBACKS = ("sample", "component_mean", "mixture_mean")
PHI_MODES = ("grounded", "free")


class _Config:
    """Shared dict round trip with strict key checking."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[C], d: dict[str, Any]) -> C:
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        for key in d:
            if key not in known:
                raise ValueError(f"unknown {cls.__name__} key {key!r}; known keys: {', '.join(sorted(known))}")
        return cls(**d)


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ValueError(msg)


@dataclass(frozen=True)
class ModelConfig(_Config):
    """The state transition model: an LSTM trunk and a deterministic or MDN head."""

    hidden_size: int = 64  # units per LSTM layer (paper: 64 reacher, 128 pick-and-place)
    num_layers: int = 3  # LSTM layers (paper: 3)
    head: str = "mdn"  # "mdn" (NLL of an isotropic Gaussian mixture) or "deterministic" (MSE)
    mixtures: int = 3  # Gaussians of the MDN head (paper: 3 reacher, 20 pick-and-place)
    sigma_min: float = 1e-3  # floor of each component's sigma, in normalised state units

    def __post_init__(self) -> None:
        _check(self.head in HEADS, f"ModelConfig.head must be one of {HEADS}, got {self.head!r}")
        _check(self.hidden_size >= 1, f"ModelConfig.hidden_size must be >= 1, got {self.hidden_size}")
        _check(self.num_layers >= 1, f"ModelConfig.num_layers must be >= 1, got {self.num_layers}")
        _check(self.mixtures >= 1, f"ModelConfig.mixtures must be >= 1, got {self.mixtures}")
        _check(self.sigma_min > 0, f"ModelConfig.sigma_min must be > 0, got {self.sigma_min}")


@dataclass(frozen=True)
class TrainConfig(_Config):
    """Optimisation and the auto-conditioning schedule."""

    iters: int = 2000  # optimizer steps
    batch_size: int = 32  # demonstrations per step (sampled without replacement when possible)
    lr: float = 1e-3  # Adam learning rate
    grad_clip: float = 1.0  # max global gradient norm (0 disables clipping)
    u: int = 5  # ground-truth steps per auto-conditioning period
    v: int = 5  # self-fed steps per period; 0 = teacher forcing
    tf_warmup: int = 0  # first iterations teacher-forced before the (u, v) schedule starts (not in the paper)
    feedback: str = "component_mean"  # what an MDN feeds back: sample | component_mean | mixture_mean
    temperature: float = 1.0  # sampling temperature when feedback == "sample"
    detach_feedback: bool = False  # stop gradients through fed-back states (acLSTM reference: no)
    phi_mode: str = "grounded"  # fed-back phi: "grounded" = FK of the integrated q, "free" = model's own
    input_noise: float = 0.0  # std of Gaussian noise on ground-truth inputs, normalised units (not in the paper)
    checkpoint_every: int = 500  # iterations between checkpoints (0: only at the end)
    log_every: int = 10  # iterations between on_metrics calls
    val_every: int = 0  # iterations between validations (0: never)
    val_episodes: int = 16  # fresh task episodes rolled out for the validation metric (stm.train.Validation)
    max_seconds: float = 0.0  # wall-clock budget of the run, resumed runs included (0: none)
    seed: int = 0

    def __post_init__(self) -> None:
        _check(self.max_seconds >= 0, f"TrainConfig.max_seconds must be >= 0, got {self.max_seconds}")
        _check(self.iters >= 0, f"TrainConfig.iters must be >= 0, got {self.iters}")
        _check(self.batch_size >= 1, f"TrainConfig.batch_size must be >= 1, got {self.batch_size}")
        _check(self.lr > 0, f"TrainConfig.lr must be > 0, got {self.lr}")
        _check(self.grad_clip >= 0, f"TrainConfig.grad_clip must be >= 0, got {self.grad_clip}")
        _check(self.u >= 1, f"TrainConfig.u must be >= 1, got {self.u}")
        _check(self.v >= 0, f"TrainConfig.v must be >= 0, got {self.v}")
        _check(self.tf_warmup >= 0, f"TrainConfig.tf_warmup must be >= 0, got {self.tf_warmup}")
        _check(self.feedback in FEEDBACKS, f"TrainConfig.feedback must be one of {FEEDBACKS}, got {self.feedback!r}")
        _check(self.input_noise >= 0, f"TrainConfig.input_noise must be >= 0, got {self.input_noise}")
        _check(self.temperature > 0, f"TrainConfig.temperature must be > 0, got {self.temperature}")
        _check(self.phi_mode in PHI_MODES, f"TrainConfig.phi_mode must be one of {PHI_MODES}, got {self.phi_mode!r}")
        for name in ("checkpoint_every", "log_every", "val_every"):
            _check(getattr(self, name) >= 0, f"TrainConfig.{name} must be >= 0, got {getattr(self, name)}")
        _check(self.val_episodes >= 1, f"TrainConfig.val_episodes must be >= 1, got {self.val_episodes}")

    @property
    def auto_conditioning(self) -> bool:
        return self.v > 0
