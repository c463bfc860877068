import math

import pytest
import torch
from torch import distributions as D

from stm import mdn


def reference_nll(logit_alpha, mu, log_sigma, target):
    sigma = log_sigma.exp().unsqueeze(-1).expand_as(mu)
    mix = D.MixtureSameFamily(D.Categorical(logits=logit_alpha), D.Independent(D.Normal(mu, sigma), 1))
    return -mix.log_prob(target)


@pytest.mark.parametrize("seed", range(6))
def test_mixture_nll_matches_torch_distributions(seed):
    g = torch.Generator().manual_seed(seed)
    lead = tuple(int(x) for x in torch.randint(1, 5, (int(torch.randint(0, 3, (1,), generator=g)),), generator=g))
    m, dim = int(torch.randint(1, 6, (1,), generator=g)), int(torch.randint(1, 14, (1,), generator=g))
    logit_alpha = torch.randn(*lead, m, generator=g, dtype=torch.float64) * 3
    mu = torch.randn(*lead, m, dim, generator=g, dtype=torch.float64)
    log_sigma = torch.empty(*lead, m, dtype=torch.float64).uniform_(-6.0, 3.0, generator=g)  # extreme sigmas
    target = torch.randn(*lead, dim, generator=g, dtype=torch.float64) * 2
    ours = mdn.mixture_nll(logit_alpha, mu, log_sigma, target)
    ref = reference_nll(logit_alpha, mu, log_sigma, target)
    assert ours.shape == lead
    torch.testing.assert_close(ours, ref, rtol=1e-5, atol=0.0)


def test_extreme_values_stay_finite_with_finite_gradients():
    logit_alpha = torch.tensor([[60.0, -60.0, 0.0]], requires_grad=True)
    mu = torch.zeros(1, 3, 13, requires_grad=True)
    log_sigma = torch.tensor([[math.log(1e-3), 8.0, -3.0]], requires_grad=True)
    target = torch.full((1, 13), 50.0)  # far from every mean under a tiny sigma
    nll = mdn.mixture_nll(logit_alpha, mu, log_sigma, target)
    nll.sum().backward()
    assert torch.isfinite(nll).all()
    for t in (logit_alpha, mu, log_sigma):
        assert torch.isfinite(t.grad).all()


def test_split_params_floors_sigma():
    raw = torch.full((2, mdn.head_size(4, 5)), -200.0)
    logit_alpha, mu, log_sigma = mdn.split_params(raw, 4, 5, sigma_min=1e-3)
    assert logit_alpha.shape == (2, 4) and mu.shape == (2, 4, 5) and log_sigma.shape == (2, 4)
    assert torch.all(log_sigma >= math.log(1e-3) - 1e-6)


def test_point_modes():
    logit_alpha = torch.tensor([[0.0, 2.0, 1.0]])
    mu = torch.tensor([[[0.0, 0.0], [1.0, 2.0], [-1.0, 4.0]]])
    log_sigma = torch.log(torch.tensor([[0.1, 0.1, 0.1]]))
    torch.testing.assert_close(mdn.component_mean(logit_alpha, mu), torch.tensor([[1.0, 2.0]]))
    w = torch.softmax(logit_alpha, -1)[0]
    torch.testing.assert_close(mdn.mixture_mean(logit_alpha, mu)[0], (w[:, None] * mu[0]).sum(0))
    with pytest.raises(ValueError, match="unknown mixture point mode"):
        mdn.point(logit_alpha, mu, log_sigma, "median")


def test_sampling_statistics_and_temperature():
    g = torch.Generator().manual_seed(0)
    n = 20000
    logit_alpha = torch.log(torch.tensor([0.3, 0.7])).expand(n, 2)
    mu = torch.tensor([[-2.0, 0.0], [3.0, 1.0]]).expand(n, 2, 2)
    log_sigma = torch.log(torch.tensor([0.5, 0.2])).expand(n, 2)
    x = mdn.sample(logit_alpha, mu, log_sigma, generator=g)
    torch.testing.assert_close(x.mean(0), mdn.mixture_mean(logit_alpha[:1], mu[:1])[0], atol=0.05, rtol=0)
    near_second = (x[:, 0] > 0.5).float().mean()
    assert abs(near_second - 0.7) < 0.02
    cold = mdn.sample(logit_alpha, mu, log_sigma, temperature=1e-4, generator=g)
    torch.testing.assert_close(cold, mu[:, 1], atol=0.02, rtol=0)  # -> the most likely component's mean


def test_sample_is_reparameterised():
    mu = torch.zeros(4, 1, 3, requires_grad=True)
    log_sigma = torch.zeros(4, 1, requires_grad=True)
    mdn.sample(torch.zeros(4, 1), mu, log_sigma, generator=torch.Generator().manual_seed(1)).sum().backward()
    assert torch.all(mu.grad == 1.0) and log_sigma.grad.abs().sum() > 0


def test_sample_component_frequencies_follow_the_tempered_weights():
    g = torch.Generator().manual_seed(3)
    n = 20000
    logits = torch.log(torch.tensor([0.2, 0.8])).expand(n, 2)
    for tau in (1.0, 0.5, 3.0):
        idx = mdn.sample_component(logits, temperature=tau, generator=g)
        assert idx.shape == (n,) and idx.dtype == torch.long
        expected = torch.softmax(logits[0] / tau, -1)[1]  # tau 0.5: 0.94, tau 3: 0.61
        assert abs(idx.float().mean() - expected) < 0.015
    with pytest.raises(ValueError, match="temperature"):
        mdn.sample_component(logits, temperature=0.0)


def test_select_and_sample_component_point_return_a_component_mean():
    mu = torch.tensor([[[0.0, 0.0], [1.0, 2.0], [-1.0, 4.0]], [[5.0, 5.0], [6.0, 6.0], [7.0, 7.0]]])
    torch.testing.assert_close(mdn.select(mu, torch.tensor([2, 0])), torch.tensor([[-1.0, 4.0], [5.0, 5.0]]))
    logits = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    x = mdn.point(logits, mu, torch.zeros(2, 3), "sample_component", generator=torch.Generator().manual_seed(0))
    assert all(any(torch.equal(x[b], mu[b, k]) for k in range(3)) for b in range(2))  # a mean, no noise added


def test_most_responsible_weighs_distance_sigma_and_weight():
    mu = torch.tensor([[[0.0, 0.0], [1.0, 0.0]]]).expand(3, 2, 2)
    logits = torch.log(torch.tensor([[0.5, 0.5], [0.5, 0.5], [0.999, 0.001]]))
    log_sigma = torch.log(torch.tensor([[0.1, 0.1], [1.0, 0.1], [0.3, 0.3]]))
    x = torch.tensor([[0.8, 0.0], [0.6, 0.0], [0.6, 0.0]])
    # the nearest; a wide component can explain a point better than a narrow nearer one; a heavy weight
    # can outvote distance
    assert mdn.most_responsible(logits, mu, log_sigma, x).tolist() == [1, 0, 0]
