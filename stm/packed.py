"""K state transition models with independent weights as one packed model.

Every parameter of stm.model.STM is stacked on a leading model axis (K, ...): the LSTM
stack steps with batched matmuls (stm.packed_cell), the head is one baddbmm, the losses
are per model. A pack is built from K ordinary STMs (`PackedSTM.from_models`, so each
model keeps the initialisation its seed gives alone) and model k comes back out as an
ordinary STM (`extract`). The optimiser (`PackedAdam`) and gradient clipping
(`clip_per_model`) act per model, so each model trains as if alone; stm.packed_train
runs the loop.
"""

from __future__ import annotations

import torch
from torch import nn

from stm import mdn
from stm.model import STM, feedback_state
from stm.packed_cell import PackedStackStepper, layer_sequence
from stm.train import _STEPPED_GT_CHUNK
from stm.windows import burn_in_state


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
        state = {n: p[k].detach().clone() for n, p in zip(self.names, self.stacked, strict=True)}
        return {**state, "state_mean": self.state_mean.clone(), "state_std": self.state_std.clone()}

    def load_model_state(self, k: int, state: dict[str, torch.Tensor]) -> None:
        """Write an STM state dict into slot k (the buffers must match the pack's)."""
        for key in ("state_mean", "state_std"):
            if not torch.equal(state[key], getattr(self, key)):
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
        ps = list(self.stacked) if idx is None else [p.index_select(0, idx) for p in self.stacked]
        return PackView(self, dict(zip(self.names, ps, strict=True)))


class PackView:
    """The tensors one unroll of a (sub-)pack reads: the LSTM layers, the head, normalisation."""

    def __init__(self, pack: PackedSTM, p: dict[str, torch.Tensor]):
        self.config, self.dim, self.is_mdn = pack.config, pack.dim, pack.is_mdn
        self.state_mean, self.state_std = pack.state_mean, pack.state_std
        self.lstm = [tuple(p[f"lstm.{w}_l{k}"] for w in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"))
                     for k in range(pack.config.num_layers)]
        self.head_w, self.head_b = p["head.weight"], p["head.bias"]  # (K, out, H), (K, out)
        self.K = self.head_w.shape[0]

    def normalize(self, s: torch.Tensor) -> torch.Tensor:
        return (s - self.state_mean) / self.state_std

    def denormalize(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.state_std + self.state_mean

    def head(self, h: torch.Tensor) -> torch.Tensor:
        """Top hidden states (K, ..., H) -> head outputs (K, ..., out)."""
        flat = h.reshape(self.K, -1, h.shape[-1])
        out = torch.baddbmm(self.head_b.unsqueeze(1), flat, self.head_w.transpose(1, 2))
        return out.view(*h.shape[:-1], out.shape[-1])

    def mixture(self, raw: torch.Tensor):
        return mdn.split_params(raw, self.config.mixtures, self.dim, self.config.sigma_min)

    def losses(self, raw: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(K,) mean per-step loss of each model over its valid steps (STM.loss per model)."""
        if self.is_mdn:
            per_step = mdn.mixture_nll(*self.mixture(raw), target)
        else:
            per_step = (raw - target).square().mean(-1)
        m = mask.to(per_step.dtype)
        return (per_step * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1.0)

    def feedback_predictor(self, mode: str, dims: int):
        """As STM.feedback_predictor, for all K models: (K, B, H) -> (K, B, dims) raw units."""
        std, mean = self.state_std[:dims], self.state_mean[:dims]
        w, b = self.head_w, self.head_b
        if not self.is_mdn:
            w_fb, b_fb = (w[:, :dims] * std[:, None]).transpose(1, 2), torch.addcmul(mean, b[:, :dims], std)
            return lambda h: torch.baddbmm(b_fb.unsqueeze(1), h, w_fb)
        if mode not in ("component_mean", "mixture_mean"):
            return None
        m, D = self.config.mixtures, self.dim
        w_mu = w[:, 2 * m:].unflatten(1, (m, D))[:, :, :dims] * std[:, None]  # (K, m, dims, H)
        b_mu = torch.addcmul(mean, b[:, 2 * m:].unflatten(1, (m, D))[:, :, :dims], std)
        w_fb = torch.cat([w[:, :m], w_mu.flatten(1, 2)], 1).transpose(1, 2)  # (K, H, m + m * dims)
        b_fb = torch.cat([b[:, :m], b_mu.flatten(1)], 1).unsqueeze(1)
        point = mdn.component_mean if mode == "component_mean" else mdn.mixture_mean

        def predict(h: torch.Tensor) -> torch.Tensor:
            out = torch.baddbmm(b_fb, h, w_fb)
            return point(out[..., :m], out[..., m:].unflatten(-1, (m, dims)))

        return predict


def fused_sequence(view: PackView, z: torch.Tensor, h: list[torch.Tensor] | None = None,
                   c: list[torch.Tensor] | None = None) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
    """Normalised inputs z (K, B, n, D) through each model's stack in one fused LSTM call per
    model (oneDNN's multi-step kernel on CPU: per model it beats any batched step for long
    known input runs); top hidden states (K, B, n, H) and per-layer (h, c) after the last step."""
    outs, hn, cn = [], [], []
    for k in range(view.K):
        flat = [t[k] for layer in view.lstm for t in layer]
        hx = None if h is None else (torch.stack([x[k] for x in h]), torch.stack([x[k] for x in c]))
        if hx is None:
            zeros = z.new_zeros(len(view.lstm), z.shape[1], view.lstm[0][1].shape[-1])
            hx = (zeros, zeros)
        out, hk, ck = torch._VF.lstm(z[k], hx, flat, True, len(view.lstm), 0.0, True, False, True)
        outs.append(out)
        hn.append(hk)
        cn.append(ck)
    hn_, cn_ = torch.stack(hn, 1), torch.stack(cn, 1)  # (L, K, B, H)
    return torch.stack(outs), list(hn_.unbind(0)), list(cn_.unbind(0))


def packed_unroll(view: PackView, states: torch.Tensor, q: torch.Tensor, psi: torch.Tensor, steps: list[int],
                  task, cfg, kin, gens: list[torch.Generator],
                  burn: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Head outputs (K, B, T, out) of K models, each under cfg's (u, v) schedule, as
    stm.train.unroll gives per model. states (K, B, T+1, D), q (K, B, T+1, 7), psi (K, B, T+1, P):
    each model's batch padded to the longest; steps[k] = model k's own T (its input noise and
    samples are drawn for its own steps only, from gens[k], so each generator advances as alone).
    burn: windows' burn-in (stm.windows), raw states (K, B, n, D) and where they are valid."""
    K, B, T1, D = states.shape
    T = T1 - 1
    mean = view.state_mean
    z_gt = view.normalize(states[:, :, :-1])
    noisy = cfg.input_noise > 0
    if noisy:  # each model's noise from its own generator, over its own steps (as train draws it)
        noise = torch.zeros_like(z_gt)
        for k in range(K):
            noise[k, :, : steps[k]] = cfg.input_noise * torch.randn((B, steps[k], D), generator=gens[k])
        z_gt = z_gt + noise
    centred = z_gt * view.state_std if noisy else states[:, :, :-1] - mean  # the stepper folds in the std
    stepper = PackedStackStepper(view.lstm, view.state_std)
    hl, cl = stepper.zeros(centred)
    if burn is not None:
        hl, cl = burn_in_state(PackedStackStepper(view.lstm, view.state_std), burn[0] - mean, burn[1], hl, cl)
    if cfg.v == 0:
        return view.head(fused_sequence(view, z_gt, *((hl, cl) if burn is not None else ()))[0])
    hs: list[torch.Tensor] = []  # top hidden states, chunks (K, B, n, H)
    layout = task.layout
    dims = layout.phi.stop if cfg.phi_mode == "free" else layout.phi.start
    point = view.feedback_predictor(cfg.feedback, dims)
    predict = (lambda h, _t: point(h)) if point is not None else _sampler(view, cfg, gens, steps)
    t = 0
    while t < T:
        n = min(cfg.u, T - t)  # ground-truth steps: stepped if few (a layer sequence's set-up costs more)
        if n > _STEPPED_GT_CHUNK or t == 0:
            h, hl, cl = layer_sequence(stepper, centred[:, :, t: t + n], hl, cl)  # (measured: beats K fused calls)
        else:
            block = []
            for j in range(n):
                hl, cl = stepper(centred[:, :, t + j], hl, cl)
                block.append(hl[-1])
            h = torch.stack(block, dim=2)
        hs.append(h)
        t += n
        if t >= T:
            break
        qt, block = q[:, :, t - 1], []
        for _ in range(min(cfg.v, T - t)):  # self-fed steps
            s, qt = feedback_state(task, kin, predict(hl[-1], t), qt, psi[:, :, t], cfg.phi_mode)
            if cfg.detach_feedback:
                s, qt = s.detach(), qt.detach()
            hl, cl = stepper(s - mean, hl, cl)
            block.append(hl[-1])
            t += 1
        hs.append(torch.stack(block, dim=2))
    return view.head(torch.cat(hs, dim=2))


def _sampler(view: PackView, cfg, gens: list[torch.Generator], steps: list[int]):
    """Sampled feedback: each model draws from its own generator, only at its own steps."""

    def predict(h: torch.Tensor, t: int) -> torch.Tensor:
        raw = view.head(h)
        out = []
        for k in range(view.K):
            la, mu, ls = view.mixture(raw[k])
            if t < steps[k]:
                out.append(mdn.sample(la, mu, ls, temperature=cfg.temperature, generator=gens[k]))
            else:  # past this model's batch: masked out, no draw
                out.append(mdn.component_mean(la, mu))
        return view.denormalize(torch.stack(out))

    return predict


def clip_per_model(params: list[torch.Tensor], max_norms: torch.Tensor) -> torch.Tensor:
    """torch.nn.utils.clip_grad_norm_ for each model of a pack: (K,) total gradient norms
    before clipping; each model's gradients scaled by min(1, max_norm_k / (norm_k + 1e-6))
    (max_norm inf: no clipping)."""
    grads = [p.grad for p in params if p.grad is not None]
    K = grads[0].shape[0]
    norms = torch.stack([torch.linalg.vector_norm(g.reshape(K, -1), dim=1) for g in grads], dim=1)
    total = torch.linalg.vector_norm(norms, dim=1)
    coef = (max_norms.to(total.dtype) / (total + 1e-6)).clamp(max=1.0)
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
        self.steps[active] += 1
        st = self.steps[active]
        step_size = (self.lr[active] / (1 - b1 ** st)).float()
        bc2_sqrt = ((1 - b2 ** st) ** 0.5).float()
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
        state = {i: {"step": torch.tensor(float(self.steps[k])), "exp_avg": m[k].clone(), "exp_avg_sq": v[k].clone()}
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
