"""Isotropic Gaussian mixtures, as in the paper: weights alpha_i, means mu_i (D)
and ONE sigma_i per component,
    g_i(s) = (2 pi sigma_i^2)^(-D/2) exp(-||s - mu_i||^2 / (2 sigma_i^2)).

Shapes: logit_alpha (..., m), mu (..., m, D), log_sigma (..., m), points (..., D).
Everything works in log space (log_softmax for the weights, logsumexp over
components), so extreme sigmas give large but finite numbers, never NaN.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

_LOG_2PI = math.log(2.0 * math.pi)


def split_params(raw: torch.Tensor, mixtures: int, dim: int, sigma_min: float) -> tuple[torch.Tensor, ...]:
    """Head output (..., m * (D + 2)) -> (logit_alpha, mu, log_sigma).

    sigma = sigma_min + softplus(raw): smooth, positive, floored at sigma_min, and
    its log never underflows (the floor keeps log_sigma >= log(sigma_min)).
    """
    m = mixtures
    logit_alpha = raw[..., :m]
    log_sigma = torch.log(sigma_min + F.softplus(raw[..., m:2 * m]))
    mu = raw[..., 2 * m:].unflatten(-1, (m, dim))
    return logit_alpha, mu, log_sigma


def head_size(mixtures: int, dim: int) -> int:
    return mixtures * (dim + 2)


def component_log_prob(mu: torch.Tensor, log_sigma: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """log g_i(target) for each component: (..., m)."""
    dim = mu.shape[-1]
    sq = (target.unsqueeze(-2) - mu).square().sum(-1)
    return -0.5 * dim * _LOG_2PI - dim * log_sigma - 0.5 * sq * torch.exp(-2.0 * log_sigma)


def mixture_nll(logit_alpha: torch.Tensor, mu: torch.Tensor, log_sigma: torch.Tensor,
                target: torch.Tensor) -> torch.Tensor:
    """Negative log-likelihood of `target` under the mixture, per element: shape (...)."""
    log_alpha = F.log_softmax(logit_alpha, dim=-1)
    return -torch.logsumexp(log_alpha + component_log_prob(mu, log_sigma, target), dim=-1)


def component_mean(logit_alpha: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
    """Mean of the most likely component (..., D); differentiable w.r.t. mu."""
    idx = logit_alpha.argmax(dim=-1, keepdim=True)  # (..., 1)
    return torch.gather(mu, -2, idx.unsqueeze(-1).expand(*idx.shape, mu.shape[-1])).squeeze(-2)


def mixture_mean(logit_alpha: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
    """sum_i alpha_i mu_i (..., D)."""
    return (torch.softmax(logit_alpha, dim=-1).unsqueeze(-1) * mu).sum(-2)


def sample_component(logit_alpha: torch.Tensor, *, temperature: float = 1.0,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """Index (...,) of one component per mixture, drawn from softmax(logits / temperature):
    tau < 1 favours the likely components, tau > 1 flattens the weights."""
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    probs = torch.softmax(logit_alpha.detach() / temperature, dim=-1)
    flat = probs.reshape(-1, probs.shape[-1])
    if generator is not None and generator.device != flat.device:  # a CPU stream for a model on a GPU
        return torch.multinomial(flat.to(generator.device), 1, generator=generator).to(flat.device).reshape(
            probs.shape[:-1])
    return torch.multinomial(flat, 1, generator=generator).reshape(probs.shape[:-1])


def select(mu: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Mean (..., D) of component idx (...,) of each mixture; differentiable w.r.t. mu."""
    idx = idx.reshape(*idx.shape, 1, 1).expand(*idx.shape, 1, mu.shape[-1])
    return torch.gather(mu, -2, idx).squeeze(-2)


def most_responsible(logit_alpha: torch.Tensor, mu: torch.Tensor, log_sigma: torch.Tensor,
                     point: torch.Tensor) -> torch.Tensor:
    """Index (...,) of the component with the highest posterior responsibility for `point` (..., D):
    argmax_i log alpha_i + log g_i(point)."""
    return (F.log_softmax(logit_alpha, dim=-1) + component_log_prob(mu, log_sigma, point)).argmax(dim=-1)


def sample(logit_alpha: torch.Tensor, mu: torch.Tensor, log_sigma: torch.Tensor, *, temperature: float = 1.0,
           generator: torch.Generator | None = None) -> torch.Tensor:
    """Draw one point per mixture (..., D).

    Temperature tau sharpens the weights (logits / tau) and scales each sigma by
    sqrt(tau); tau -> 0 approaches the component mean. The draw is reparameterised
    (mu + sigma * eps), so gradients flow to mu and sigma of the chosen component.
    """
    idx = sample_component(logit_alpha, temperature=temperature, generator=generator)
    mu_k = select(mu, idx)
    sigma_k = torch.exp(torch.gather(log_sigma, -1, idx.unsqueeze(-1))) * math.sqrt(temperature)
    device = mu.device if generator is None else generator.device  # the generator's stream, on any device
    eps = torch.randn(mu_k.shape, generator=generator, dtype=mu.dtype, device=device).to(mu.device)
    return mu_k + sigma_k * eps


POINT_MODES = ("sample", "sample_component", "component_mean", "mixture_mean")


def point(logit_alpha: torch.Tensor, mu: torch.Tensor, log_sigma: torch.Tensor, mode: str, *,
          temperature: float = 1.0, generator: torch.Generator | None = None) -> torch.Tensor:
    """One point of the mixture chosen by `mode`: sample (a draw), sample_component (the mean
    of a component drawn with the temperature), component_mean (of the most likely
    component) or mixture_mean."""
    if mode == "component_mean":
        return component_mean(logit_alpha, mu)
    if mode == "mixture_mean":
        return mixture_mean(logit_alpha, mu)
    if mode == "sample":
        return sample(logit_alpha, mu, log_sigma, temperature=temperature, generator=generator)
    if mode == "sample_component":
        return select(mu, sample_component(logit_alpha, temperature=temperature, generator=generator))
    raise ValueError(f"unknown mixture point mode {mode!r}; known: {', '.join(POINT_MODES)}")
