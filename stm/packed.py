"""K state transition models with independent weights as one packed model.

Every parameter of stm.model.STM is stacked on a leading model axis (K, ...): the LSTM
stack steps with batched matmuls (stm.packed_lstm_step), the head is one baddbmm, the losses
are per model. A pack is built from K ordinary STMs (`PackedSTM.from_models`, so each
model keeps the initialisation its seed gives alone) and model k comes back out as an
ordinary STM (`extract`). The optimiser (`PackedAdam`) and gradient clipping
(`clip_per_model`) act per model, so each model trains as if alone; stm.training.autoconditioning
unrolls a pack and stm.training.loop runs the loop (a single model is a pack of one); stm.rollout
generates with a pack in one batched loop.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from stm import mdn
from stm.model import STM, step_losses


class PackedSTM(nn.Module):
    """The parameters of K STMs of one model config, stacked: `stacked[i]` is (K, *shape of
    the STM's i-th parameter), in STM.named_parameters() order. The normalisation buffers
    are shared (one dataset per pack)."""

    def __init__(self, template: STM, stacked: list[torch.Tensor]):
        super().__init__()
        self.config, self.layout, self.phi_mode, self.dim = template.config, template.layout, template.phi_mode, \
            template.dim
        self.names = [n for n, _ in template.named_parameters()]
        if len(stacked) != len(self.names):
            raise ValueError(f"a pack needs {len(self.names)} stacked parameters, got {len(stacked)}")
        self.stacked = nn.ParameterList([nn.Parameter(p) for p in stacked])
        self.register_buffer("state_mean", template.state_mean.clone())
        self.register_buffer("state_std", template.state_std.clone())
        self.K = stacked[0].shape[0]

    @classmethod
    def from_models(cls, models: list[STM]) -> PackedSTM:
        first = models[0]
        for m in models[1:]:
            if m.config != first.config or m.layout != first.layout or m.phi_mode != first.phi_mode:
                raise ValueError("a pack holds models of one config, state layout and phi_mode")
            if not (torch.equal(m.state_mean, first.state_mean) and torch.equal(m.state_std, first.state_std)):
                raise ValueError("a pack holds models normalised alike (one dataset)")
        params = [dict(m.named_parameters()) for m in models]
        return cls(first, [torch.stack([p[n].detach() for p in params]).clone() for n, _ in first.named_parameters()])

    @property
    def is_mdn(self) -> bool:
        return self.config.head == "mdn"

    def model_state(self, k: int) -> dict[str, torch.Tensor]:
        """Model k's state dict in STM's format (weights and normalisation buffers)."""
        state = {n: p[k].detach().cpu().clone() for n, p in zip(self.names, self.stacked, strict=True)}
        return {**state, "state_mean": self.state_mean.cpu().clone(), "state_std": self.state_std.cpu().clone()}

    def load_model_state(self, k: int, state: dict[str, torch.Tensor]) -> None:
        """Write an STM state dict into slot k (the buffers must match the pack's)."""
        for key in ("state_mean", "state_std"):
            if not torch.equal(state[key].to(self.state_mean.device), getattr(self, key)):
                raise ValueError(f"model {k}'s {key} differs from the pack's (another dataset?)")
        with torch.no_grad():
            for n, p in zip(self.names, self.stacked, strict=True):
                p[k].copy_(state[n])

    def extract(self, k: int) -> STM:
        """Model k as an ordinary STM (a copy, eval mode)."""
        model = STM(self.config, self.layout, self.state_mean, self.state_std, phi_mode=self.phi_mode)
        model.load_state_dict(self.model_state(k))
        return model.eval()

    def view(self, idx: torch.Tensor | None = None) -> PackView:
        """The parameters of models idx (all when None) for one unroll; gradients reach the pack."""
        if idx is not None:
            idx = idx.to(self.state_mean.device)
        ps = list(self.stacked) if idx is None else [p.index_select(0, idx) for p in self.stacked]
        return PackView(self, dict(zip(self.names, ps, strict=True)))


class PackView:
    """The tensors one unroll of a (sub-)pack reads: the LSTM layers, the head, normalisation."""

    def __init__(self, pack: PackedSTM | STM, p: dict[str, torch.Tensor]):
        self.config, self.dim, self.is_mdn = pack.config, pack.dim, pack.is_mdn
        self.state_mean, self.state_std = pack.state_mean, pack.state_std
        self.lstm = [tuple(p[f"lstm.{w}_l{k}"] for w in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"))
                     for k in range(pack.config.num_layers)]
        self.head_w, self.head_b = p["head.weight"], p["head.bias"]  # (K, out, H), (K, out)
        self.K = self.head_w.shape[0]
        self.matmul_dtype: torch.dtype | None = None  # the head's products in it (None: float32)

    def with_products(self, dtype: torch.dtype | None) -> PackView:
        """This view with the head's products in `dtype` (stm.lstm_step.product_dtype; None: float32)."""
        if dtype is self.matmul_dtype:
            return self
        view = copy.copy(self)
        view.matmul_dtype = dtype
        return view

    @classmethod
    def of_model(cls, model: STM) -> PackView:
        """One STM as a pack of one, on the model's own parameters (gradients reach them)."""
        return cls(model, {n: p.unsqueeze(0) for n, p in model.named_parameters()})

    def normalize(self, s: torch.Tensor) -> torch.Tensor:
        return (s - self.state_mean) / self.state_std

    def denormalize(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.state_std + self.state_mean

    def head(self, h: torch.Tensor) -> torch.Tensor:
        """Top hidden states (K, ..., H) -> head outputs (K, ..., out)."""
        flat = h.reshape(self.K, -1, h.shape[-1])
        dt = self.matmul_dtype
        if dt is None:
            out = torch.baddbmm(self.head_b.unsqueeze(1), flat, self.head_w.transpose(1, 2))
        else:
            w_t = self.head_w.transpose(1, 2).to(dt)
            out = torch.baddbmm(self.head_b.unsqueeze(1).to(dt), flat.to(dt), w_t).float()
        return out.view(*h.shape[:-1], out.shape[-1])

    def mixture(self, raw: torch.Tensor):
        return mdn.split_params(raw, self.config.mixtures, self.dim, self.config.sigma_min)

    predict = STM.predict  # head outputs -> a predicted next state, as one model's (it reads what a view has too)

    def losses(self, raw: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, kernel: str = "python"
               ) -> torch.Tensor:
        """(K,) mean per-step loss of each model over its valid steps (STM.loss per model; stm.model.step_losses)."""
        per_step = step_losses(raw, target, self.config, kernel)
        m = mask.to(per_step.dtype)
        return (per_step * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1.0)

    def feedback_weights(self, mode: str, dims: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The head rows the feedback reads, with the denormalisation folded in: (w (K, H, O), b (K, 1, O)),
        O = dims (deterministic head) or m + m * dims (the mixture logits, then the first `dims` mean coordinates
        per component; no sigmas). None where that does not apply (sampling needs the sigmas)."""
        std, mean = self.state_std[:dims], self.state_mean[:dims]
        w, b = self.head_w, self.head_b
        if not self.is_mdn:
            return (w[:, :dims] * std[:, None]).transpose(1, 2), torch.addcmul(mean, b[:, :dims], std).unsqueeze(1)
        if mode not in ("component_mean", "mixture_mean"):
            return None
        m, D = self.config.mixtures, self.dim
        w_mu = w[:, 2 * m:].unflatten(1, (m, D))[:, :, :dims] * std[:, None]  # (K, m, dims, H)
        b_mu = torch.addcmul(mean, b[:, 2 * m:].unflatten(1, (m, D))[:, :, :dims], std)
        w_fb = torch.cat([w[:, :m], w_mu.flatten(1, 2)], 1).transpose(1, 2)  # (K, H, m + m * dims)
        return w_fb, torch.cat([b[:, :m], b_mu.flatten(1)], 1).unsqueeze(1)

    def feedback_predictor(self, mode: str, dims: int):
        """As STM.feedback_predictor, for all K models: (K, B, H) -> (K, B, dims) raw units."""
        wb = self.feedback_weights(mode, dims)
        if wb is None:
            return None
        w_fb, b_fb = wb
        dt = self.matmul_dtype
        if dt is not None:  # cast once per unroll
            w_fb, b_fb = w_fb.to(dt), b_fb.to(dt)

        def product(h: torch.Tensor) -> torch.Tensor:
            return torch.baddbmm(b_fb, h, w_fb) if dt is None else torch.baddbmm(b_fb, h.to(dt), w_fb).float()

        if not self.is_mdn:
            return product
        m = self.config.mixtures
        point = mdn.component_mean if mode == "component_mean" else mdn.mixture_mean

        def predict(h: torch.Tensor) -> torch.Tensor:
            out = product(h)
            return point(out[..., :m], out[..., m:].unflatten(-1, (m, dims)))

        return predict


def clip_per_model(params: list[torch.Tensor], max_norms: torch.Tensor) -> torch.Tensor:
    """torch.nn.utils.clip_grad_norm_ for each model of a pack: (K,) total gradient norms
    before clipping; each model's gradients scaled by min(1, max_norm_k / (norm_k + 1e-6))
    (max_norm inf: no clipping)."""
    grads = [p.grad for p in params if p.grad is not None]
    K = grads[0].shape[0]
    norms = torch.stack([torch.linalg.vector_norm(g.reshape(K, -1), dim=1) for g in grads], dim=1)
    total = torch.linalg.vector_norm(norms, dim=1)
    coef = (max_norms.to(total.device, total.dtype) / (total + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.view(K, *[1] * (g.dim() - 1)))
    return total


class PackedAdam:
    """torch.optim.Adam (defaults, single-tensor path) for each model of a pack: per model its
    own step count and learning rate, and only the models in `active` move."""

    def __init__(self, params: list[torch.Tensor], lrs: list[float], betas=(0.9, 0.999), eps: float = 1e-8):
        self.params, self.betas, self.eps = params, betas, eps
        K = params[0].shape[0]
        self.lr = torch.tensor(lrs, dtype=torch.float64)
        self.steps = torch.zeros(K, dtype=torch.float64)
        self.exp_avg = [torch.zeros_like(p) for p in params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in params]

    @torch.no_grad()
    def step(self, active: torch.Tensor) -> None:
        """One Adam step for the models whose indices are in `active` (long)."""
        b1, b2 = self.betas
        K = self.steps.shape[0]
        full = len(active) == K
        self.steps[active] += 1  # step counts and learning rates: float64 on the CPU, as torch.optim.Adam's
        st = self.steps[active]
        device = self.params[0].device
        step_size = (self.lr[active] / (1 - b1 ** st)).float().to(device)
        bc2_sqrt = ((1 - b2 ** st) ** 0.5).float().to(device)
        active = active.to(device)
        for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq, strict=True):
            shape = (len(active), *[1] * (p.dim() - 1))
            g = p.grad if full else p.grad.index_select(0, active)
            pk, mk, vk = (p, m, v) if full else (p.index_select(0, active), m.index_select(0, active),
                                                  v.index_select(0, active))
            mk.lerp_(g, 1 - b1)
            vk.mul_(b2).addcmul_(g, g, value=1 - b2)
            denom = (vk.sqrt() / bc2_sqrt.view(shape)).add_(self.eps)
            pk.add_((mk * -step_size.view(shape)) / denom)  # = addcdiv_(m, denom, value=-step_size)
            if not full:
                p.index_copy_(0, active, pk)
                m.index_copy_(0, active, mk)
                v.index_copy_(0, active, vk)

    def model_state(self, k: int, template: dict) -> dict:
        """Model k's optimiser state in torch.optim.Adam's state_dict format (`template`: the
        state_dict of an Adam over the extracted model, for its param_groups)."""
        state = {i: {"step": torch.tensor(float(self.steps[k])), "exp_avg": m[k].cpu().clone(),
                     "exp_avg_sq": v[k].cpu().clone()}
                 for i, (m, v) in enumerate(zip(self.exp_avg, self.exp_avg_sq, strict=True))}
        groups = [{**g, "lr": float(self.lr[k])} for g in template["param_groups"]]
        return {"state": state if self.steps[k] > 0 else {}, "param_groups": groups}

    def load_model_state(self, k: int, state: dict) -> None:
        """Slot k from a torch.optim.Adam state_dict of one model (as a single-model checkpoint holds)."""
        group = state["param_groups"][0]
        if tuple(group["betas"]) != tuple(self.betas) or group["eps"] != self.eps or group["weight_decay"] or \
                group["amsgrad"]:
            raise ValueError("the checkpoint's optimiser is not a default Adam")
        self.lr[k] = group["lr"]
        st = state["state"]
        self.steps[k] = float(st[0]["step"]) if st else 0.0
        for i, (m, v) in enumerate(zip(self.exp_avg, self.exp_avg_sq, strict=True)):
            m[k] = st[i]["exp_avg"] if st else 0.0
            v[k] = st[i]["exp_avg_sq"] if st else 0.0
