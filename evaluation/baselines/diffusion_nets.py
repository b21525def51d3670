"""The transformer noise-prediction network of Diffusion Policy (Chi et al. 2023), ported module for
module from the reference repository (real-stanford/diffusion_policy, ``TransformerForDiffusion``
with time and observations as condition tokens, causal attention and an MLP condition encoder).
Neither LeRobot (whose ``DiffusionPolicy`` is the 1-D U-Net only) nor diffusers has it; the
diffusion process is diffusers' (diffusion_policy.py). Inputs and outputs are action chunks
(B, horizon, action_dim)."""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freq = torch.exp(-math.log(10000.0) / (half - 1) * torch.arange(half, device=t.device))
        arg = t.float()[:, None] * freq[None]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


class TransformerForDiffusion(nn.Module):
    """The reference transformer (``time_as_cond``, ``obs_as_cond``, ``causal_attn``,
    ``n_cond_layers`` 0): a decoder over the action tokens whose memory is the diffusion-step token
    and one token per observation step passed through an MLP; an action token sees earlier action
    tokens, the step token and the observations up to its own time."""

    def __init__(self, action_dim: int, obs_dim: int, horizon: int, n_obs: int, n_layer: int = 8,
                 n_head: int = 4, n_emb: int = 256, p_drop_emb: float = 0.0, p_drop_attn: float = 0.01) -> None:
        super().__init__()
        self.input_emb = nn.Linear(action_dim, n_emb)
        self.pos_emb = nn.Parameter(torch.zeros(1, horizon, n_emb))
        self.drop = nn.Dropout(p_drop_emb)
        self.time_emb = SinusoidalPosEmb(n_emb)
        self.cond_obs_emb = nn.Linear(obs_dim, n_emb)
        self.cond_pos_emb = nn.Parameter(torch.zeros(1, 1 + n_obs, n_emb))
        self.encoder = nn.Sequential(nn.Linear(n_emb, 4 * n_emb), nn.Mish(), nn.Linear(4 * n_emb, n_emb))
        layer = nn.TransformerDecoderLayer(n_emb, n_head, 4 * n_emb, p_drop_attn, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.decoder = nn.TransformerDecoder(layer, n_layer)
        self.ln_f = nn.LayerNorm(n_emb)
        self.head = nn.Linear(n_emb, action_dim)
        t, s = torch.arange(horizon), torch.arange(1 + n_obs)
        self.register_buffer("mask", torch.where(t[:, None] >= t[None], 0.0, float("-inf")), persistent=False)
        self.register_buffer("memory_mask", torch.where(t[:, None] >= s[None] - 1, 0.0, float("-inf")),
                             persistent=False)
        self.apply(self._init_weights)
        nn.init.normal_(self.pos_emb, std=0.02)
        nn.init.normal_(self.cond_pos_emb, std=0.02)

    @staticmethod
    def _init_weights(module: nn.Module) -> None:
        """The reference initialization: linear and attention weights N(0, 0.02), biases 0, norms 1 / 0."""
        if isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, std=0.02)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.MultiheadAttention):
            for name in ("in_proj_weight", "q_proj_weight", "k_proj_weight", "v_proj_weight"):
                if getattr(module, name) is not None:
                    nn.init.normal_(getattr(module, name), std=0.02)
            for name in ("in_proj_bias", "bias_k", "bias_v"):
                if getattr(module, name) is not None:
                    nn.init.zeros_(getattr(module, name))
        elif isinstance(module, nn.LayerNorm):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)

    def forward(self, x: torch.Tensor, t: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        cond = torch.cat([self.time_emb(t)[:, None], self.cond_obs_emb(obs)], dim=1)
        memory = self.encoder(self.drop(cond + self.cond_pos_emb))
        h = self.drop(self.input_emb(x) + self.pos_emb[:, : x.shape[1]])
        h = self.decoder(h, memory, tgt_mask=self.mask, memory_mask=self.memory_mask)
        return self.head(self.ln_f(h))

    def param_groups(self, weight_decay: float) -> list[dict]:
        """As the reference: weight decay on the weights of linear and attention layers only."""
        decay, no_decay = [], []
        for name, p in self.named_parameters():
            (decay if p.ndim >= 2 and "pos_emb" not in name else no_decay).append(p)
        return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
