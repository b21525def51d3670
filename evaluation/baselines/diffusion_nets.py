"""The two noise-prediction networks of Diffusion Policy (Chi et al. 2023), written from the
paper's description: a 1-D temporal U-Net with FiLM conditioning on the diffusion step and the
observations, and a time-series transformer decoder with the observations as cross-attention
tokens. Inputs are action sequences (B, horizon, action_dim)."""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalEmbedding(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freq = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device) / (half - 1))
        arg = t.float()[:, None] * freq[None]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


class ConvBlock(nn.Sequential):
    def __init__(self, cin: int, cout: int, kernel: int, groups: int) -> None:
        super().__init__(nn.Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(groups, cout), nn.Mish())


class FiLMResBlock(nn.Module):
    """Two conv blocks; the condition predicts a per-channel scale and bias applied between them."""

    def __init__(self, cin: int, cout: int, cond_dim: int, kernel: int, groups: int) -> None:
        super().__init__()
        self.first = ConvBlock(cin, cout, kernel, groups)
        self.second = ConvBlock(cout, cout, kernel, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * cout))
        self.skip = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.first(x)
        scale, bias = self.film(cond).unsqueeze(-1).chunk(2, dim=1)
        h = self.second(scale * h + bias)
        return h + self.skip(x)


class ConditionalUnet1D(nn.Module):
    def __init__(self, action_dim: int, cond_dim: int, down_dims: tuple[int, ...] = (256, 512, 1024),
                 kernel: int = 5, groups: int = 8, step_embed: int = 256) -> None:
        super().__init__()
        self.step_encoder = nn.Sequential(SinusoidalEmbedding(step_embed), nn.Linear(step_embed, 4 * step_embed),
                                          nn.Mish(), nn.Linear(4 * step_embed, step_embed))
        c = step_embed + cond_dim
        dims = [action_dim, *down_dims]
        pairs = list(zip(dims[:-1], dims[1:], strict=True))
        self.down = nn.ModuleList()
        for i, (cin, cout) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(nn.ModuleList([
                FiLMResBlock(cin, cout, c, kernel, groups), FiLMResBlock(cout, cout, c, kernel, groups),
                nn.Identity() if last else nn.Conv1d(cout, cout, 3, stride=2, padding=1)]))
        mid = down_dims[-1]
        self.mid = nn.ModuleList([FiLMResBlock(mid, mid, c, kernel, groups), FiLMResBlock(mid, mid, c, kernel, groups)])
        self.up = nn.ModuleList()
        for cin, cout in reversed(pairs[1:]):  # every up level undoes one down-sampling
            self.up.append(nn.ModuleList([
                FiLMResBlock(2 * cout, cin, c, kernel, groups), FiLMResBlock(cin, cin, c, kernel, groups),
                nn.ConvTranspose1d(cin, cin, 4, stride=2, padding=1)]))
        # a full-resolution level for the first skip, which Chi et al.'s net leaves unused: without it
        # every input value passes a down_dims[0] x horizon/2 bottleneck (160 x 8 = 1280 here), fewer
        # values than a chunk of our 150-D actions has (16 x 150 = 2400), and the net cannot even
        # predict the noise it is given (training loss stays at 1.0; docs/baselines.md)
        d0 = down_dims[0]
        self.up.append(nn.ModuleList([FiLMResBlock(2 * d0, d0, c, kernel, groups),
                                      FiLMResBlock(d0, d0, c, kernel, groups), nn.Identity()]))
        self.head = nn.Sequential(ConvBlock(down_dims[0], down_dims[0], kernel, groups),
                                  nn.Conv1d(down_dims[0], action_dim, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """x: (B,H,A) noisy actions, t: (B,) diffusion steps, obs: (B, n_obs, obs_dim) -> (B,H,A) noise."""
        cond = torch.cat([self.step_encoder(t), obs.flatten(1)], dim=-1)
        h = x.transpose(1, 2)
        skips = []
        for res1, res2, down in self.down:
            h = res2(res1(h, cond), cond)
            skips.append(h)
            h = down(h)
        for res in self.mid:
            h = res(h, cond)
        for res1, res2, up in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(res2(res1(h, cond), cond))
        return self.head(h).transpose(1, 2)


class TransformerForDiffusion(nn.Module):
    """Decoder-only over action tokens; the memory is [diffusion step, obs_1..obs_n] tokens.
    Causal: an action token sees earlier action tokens, the step token and observations up to its time."""

    def __init__(self, action_dim: int, obs_dim: int, horizon: int, n_obs: int, n_layer: int = 8,
                 n_head: int = 4, n_emb: int = 256, p_drop_emb: float = 0.0, p_drop_attn: float = 0.3) -> None:
        super().__init__()
        self.input_emb = nn.Linear(action_dim, n_emb)
        self.pos_emb = nn.Parameter(torch.zeros(1, horizon, n_emb))
        self.step_emb = SinusoidalEmbedding(n_emb)
        self.obs_emb = nn.Linear(obs_dim, n_emb)
        self.cond_pos_emb = nn.Parameter(torch.zeros(1, 1 + n_obs, n_emb))
        self.drop = nn.Dropout(p_drop_emb)
        self.encoder = nn.Sequential(nn.Linear(n_emb, 4 * n_emb), nn.Mish(), nn.Linear(4 * n_emb, n_emb))
        layer = nn.TransformerDecoderLayer(n_emb, n_head, 4 * n_emb, p_drop_attn, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.decoder = nn.TransformerDecoder(layer, n_layer)
        self.ln_f = nn.LayerNorm(n_emb)
        self.head = nn.Linear(n_emb, action_dim)
        t = torch.arange(horizon)
        s = torch.arange(1 + n_obs)
        self.register_buffer("tgt_mask", torch.where(t[:, None] >= t[None], 0.0, float("-inf")), persistent=False)
        self.register_buffer("mem_mask", torch.where(t[:, None] >= s[None] - 1, 0.0, float("-inf")),
                             persistent=False)
        nn.init.normal_(self.pos_emb, std=0.02)
        nn.init.normal_(self.cond_pos_emb, std=0.02)

    def forward(self, x: torch.Tensor, t: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        cond = torch.cat([self.step_emb(t)[:, None], self.obs_emb(obs)], dim=1)
        memory = self.encoder(self.drop(cond + self.cond_pos_emb))
        h = self.drop(self.input_emb(x) + self.pos_emb[:, : x.shape[1]])
        h = self.decoder(h, memory, tgt_mask=self.tgt_mask, memory_mask=self.mem_mask)
        return self.head(self.ln_f(h))

    def param_groups(self, weight_decay: float) -> list[dict]:
        """Decay only the weight matrices of linear layers (not biases, norms or position embeddings)."""
        decay, no_decay = [], []
        for name, p in self.named_parameters():
            (decay if p.ndim >= 2 and "pos_emb" not in name and "norm" not in name else no_decay).append(p)
        return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
