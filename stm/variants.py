"""The variant registry: the four models of the ablation as data entries.

A variant fixes what defines it (head, teacher forcing or auto-conditioning)
and leaves every other setting to the configs it is applied to. Adding a
variant is one more entry in VARIANTS.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from stm.config import ModelConfig, TrainConfig


class UnknownVariantError(KeyError):
    def __str__(self) -> str:
        return self.args[0]


@dataclass(frozen=True)
class Variant:
    name: str
    head: str  # "mdn" | "deterministic"
    auto_conditioning: bool
    description: str
    model_overrides: dict[str, Any] = field(default_factory=dict)
    train_overrides: dict[str, Any] = field(default_factory=dict)

    def configs(self, model: ModelConfig, train: TrainConfig) -> tuple[ModelConfig, TrainConfig]:
        """Apply the variant: its head, its training mode, then its overrides.

        Teacher-forcing variants force v = 0; auto-conditioning variants keep the
        given u, v (and fail if v = 0, which would silently mean teacher forcing).
        """
        model = replace(model, head=self.head, **self.model_overrides)
        train = replace(train, **self.train_overrides)
        if not self.auto_conditioning:
            train = replace(train, v=0)
        elif train.v == 0:
            raise ValueError(f"variant {self.name!r} uses auto-conditioning but the train config has v = 0")
        return model, train


def _entries(*variants: Variant) -> dict[str, Variant]:
    return {v.name: v for v in variants}


VARIANTS: dict[str, Variant] = _entries(
    Variant("lstm", "deterministic", False, "LSTM, deterministic head (MSE), teacher forcing"),
    Variant("ac-lstm", "deterministic", True, "LSTM, deterministic head (MSE), auto-conditioning (u gt, v self)"),
    Variant("lstm-mdn", "mdn", False, "LSTM-MDN, isotropic Gaussian mixture head (NLL), teacher forcing"),
    Variant("ac-lstm-mdn", "mdn", True, "LSTM-MDN (NLL), auto-conditioning (u gt, v self): the paper's model"),
)


def get_variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise UnknownVariantError(f"unknown variant {name!r}; known variants: {', '.join(VARIANTS)}") from None
