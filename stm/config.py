"""Model and training configuration: two frozen dataclasses, plain data, validated by pydantic.

Every number that shapes a trained model lives here, so that it can be logged,
hashed, swept and stored in a checkpoint (`to_dict` / `from_dict`). Each field is
defined once, with its type and allowed values: construction (and
`dataclasses.replace`) raises `pydantic.ValidationError`, a `ValueError`, naming the
field. Strict types: a string or a bool is not an integer (config values come from
TOML and the command line); an integer is accepted for a float.
"""

from __future__ import annotations

from dataclasses import asdict, fields
from typing import Annotated, Any, ClassVar, Literal, TypeVar, get_args

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass

C = TypeVar("C", bound="_Config")

STRICT = ConfigDict(strict=True, extra="forbid")  # shared by every config dataclass of the project

Head = Literal["mdn", "deterministic"]
Feedback = Literal["sample", "component_mean", "mixture_mean"]  # what an MDN's output feeds back
PhiMode = Literal["grounded", "free"]
StepKernel = Literal["auto", "python", "cpp"]  # the unroll's steps and loss: C++ ops where built, or Python ATen calls
MatmulDtype = Literal["float32", "bfloat16"]  # dtype of the training step's matrix products (stm.lstm_step)
HEADS: tuple[str, ...] = get_args(Head)
FEEDBACKS: tuple[str, ...] = get_args(Feedback)
PHI_MODES: tuple[str, ...] = get_args(PhiMode)

PositiveInt = Annotated[int, Field(ge=1)]
NonNegativeInt = Annotated[int, Field(ge=0)]
PositiveFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]


class _Config:
    """Shared dict round trip with strict key checking."""

    # fields added after studies were stored -> their defaults: left out of hashed_dict while at them, so those
    # studies' cells keep their config hashes (tests/test_experiments_config.py) and re-runs skip them
    LATER_DEFAULTS: ClassVar[dict[str, Any]] = {}
    # how a result is computed, not what it is (an equivalent route, held to the reference by tests): never
    # hashed, so a cell may resume on another route; the run records it (experiments.cell_run.cell_params)
    UNHASHED: ClassVar[frozenset[str]] = frozenset()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)  # type: ignore[call-overload]

    def hashed_dict(self) -> dict[str, Any]:
        """What a cell's config hash (and its logged params) holds: to_dict less later fields at their defaults
        and less the unhashed ones."""
        return {k: v for k, v in self.to_dict().items()
                if k not in self.UNHASHED and not (k in self.LATER_DEFAULTS and v == self.LATER_DEFAULTS[k])}

    @classmethod
    def from_dict(cls: type[C], d: dict[str, Any]) -> C:
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        for key in d:
            if key not in known:
                raise ValueError(f"unknown {cls.__name__} key {key!r}; known keys: {', '.join(sorted(known))}")
        return cls(**d)


@dataclass(frozen=True, config=STRICT)
class ModelConfig(_Config):
    """The state transition model: an LSTM trunk and a deterministic or MDN head."""

    hidden_size: PositiveInt = 64  # units per LSTM layer (paper: 64 reacher, 128 pick-and-place)
    num_layers: PositiveInt = 3  # LSTM layers (paper: 3)
    head: Head = "mdn"  # "mdn" (NLL of an isotropic Gaussian mixture) or "deterministic" (MSE)
    mixtures: PositiveInt = 3  # Gaussians of the MDN head (paper: 3 reacher, 20 pick-and-place)
    sigma_min: PositiveFloat = 1e-3  # floor of each component's sigma, in normalised state units


@dataclass(frozen=True, config=STRICT)
class TrainConfig(_Config):
    """Optimisation and the auto-conditioning schedule."""

    LATER_DEFAULTS: ClassVar[dict[str, Any]] = {"hold_steps": 0, "window": 0, "burn_in": 0, "matmul_dtype": "float32"}
    UNHASHED: ClassVar[frozenset[str]] = frozenset({"step_kernel"})

    iters: NonNegativeInt = 2000  # optimizer steps
    batch_size: PositiveInt = 32  # demonstrations per step (sampled without replacement when possible)
    lr: PositiveFloat = 1e-3  # Adam learning rate
    grad_clip: NonNegativeFloat = 1.0  # max global gradient norm (0 disables clipping)
    u: PositiveInt = 5  # ground-truth steps per auto-conditioning period
    v: NonNegativeInt = 5  # self-fed steps per period; 0 = teacher forcing
    tf_warmup: NonNegativeInt = 0  # first iterations teacher-forced before the (u, v) schedule (not in the paper)
    feedback: Feedback = "component_mean"  # what an MDN feeds back: sample | component_mean | mixture_mean
    temperature: PositiveFloat = 1.0  # sampling temperature when feedback == "sample"
    detach_feedback: bool = False  # stop gradients through fed-back states (acLSTM reference: no)
    phi_mode: PhiMode = "grounded"  # fed-back phi: "grounded" = FK of the integrated q, "free" = model's own
    input_noise: NonNegativeFloat = 0.0  # std of Gaussian noise on ground-truth inputs, normalised (not in the paper)
    hold_steps: NonNegativeInt = 0  # steps of holding still trained after each demo (Demos.with_hold; not in the paper)
    # steps of a demo trained per sample (0: the whole demo; stm.training.windows; not in the paper)
    window: NonNegativeInt = 0
    burn_in: NonNegativeInt = 0  # with window: ground-truth steps before it that warm the state, no gradient
    # "cpp": the unroll's steps as C++ ops (stm.self_fed) and the MDN loss as one fused C++ op (stm.mdn_fused); same
    # maths as "python", float32 rounding apart; the Python steps where it does not apply (sampled or mixture_mean
    # feedback, a GPU), an error where the extension cannot be built. "auto": "cpp" where the extension builds, else
    # "python" with one warning (stm.cpp_ext.step_kernel). Unhashed: a cell may resume on either
    step_kernel: StepKernel = "auto"
    # the matrix products of the LSTM stack and the head (forward and backward) in this dtype; state, elementwise
    # maths, kinematics, loss, master weights and Adam stay float32 (stm.lstm_step.product_dtype)
    matmul_dtype: MatmulDtype = "float32"
    checkpoint_every: NonNegativeInt = 500  # iterations between checkpoints (0: only at the end)
    log_every: NonNegativeInt = 10  # iterations between on_metrics calls
    val_every: NonNegativeInt = 0  # iterations between validations (0: never)
    val_episodes: PositiveInt = 16  # fresh task episodes rolled out for the validation metric (stm.training.validation)
    max_seconds: NonNegativeFloat = 0.0  # wall-clock budget of the run, resumed runs included (0: none)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.burn_in and not self.window:
            raise ValueError(f"burn_in needs a window (burn_in={self.burn_in}, window=0: whole demos have no burn-in)")
