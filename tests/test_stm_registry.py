import pytest

from stm.config import ModelConfig, TrainConfig
from stm.variants import VARIANTS, UnknownVariantError, get_variant


def test_the_four_variants():
    assert list(VARIANTS) == ["lstm", "ac-lstm", "lstm-mdn", "ac-lstm-mdn"]
    expect = {"lstm": ("deterministic", False), "ac-lstm": ("deterministic", True),
              "lstm-mdn": ("mdn", False), "ac-lstm-mdn": ("mdn", True)}
    for name, (head, ac) in expect.items():
        v = get_variant(name)
        assert (v.name, v.head, v.auto_conditioning) == (name, head, ac) and v.description
        m, t = v.configs(ModelConfig(hidden_size=16, mixtures=4), TrainConfig(u=3, v=2, lr=5e-4))
        assert m.head == head and m.hidden_size == 16 and m.mixtures == 4 and t.lr == 5e-4
        assert (t.v > 0) == ac and t.u == 3
        assert t.v == (2 if ac else 0)


def test_unknown_variant_lists_the_known_ones():
    with pytest.raises(UnknownVariantError, match="unknown variant 'gru'.*lstm, ac-lstm, lstm-mdn, ac-lstm-mdn"):
        get_variant("gru")


def test_auto_conditioning_variant_rejects_v_zero():
    with pytest.raises(ValueError, match="v = 0"):
        get_variant("ac-lstm").configs(ModelConfig(), TrainConfig(v=0))
