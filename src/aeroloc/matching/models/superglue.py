"""SuperGlue (Sarlin et al., CVPR 2020): keypoint positions+scores encoded into SuperPoint descriptors, 9 x
(self, cross) attention layers, then optimal transport with a learned dustbin score.

Our own implementation; parameter names and shapes equal Magic Leap's ``superglue_outdoor.pth`` /
``superglue_indoor.pth`` so those checkpoints load strictly. Two layout details matter for that: multi-head
attention splits channel c into (c // heads, head c % heads), and every MLP is one ``nn.Sequential`` of
Conv1d(k=1) [+ BatchNorm1d + ReLU] blocks.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource, load_state_dict
from aeroloc.matching.models.base import Features, choose_weights, load_strict, merge_conf, to_device

_URL = "https://github.com/magicleap/SuperGluePretrainedNetwork/raw/master/models/weights/superglue_{}.pth"
SUPERGLUE_WEIGHTS = {
    kind: WeightSource(
        filename=f"superglue_{kind}.pth", url=_URL.format(kind), note="Magic Leap's SuperGlue (non-commercial licence)"
    )
    for kind in ("outdoor", "indoor")
}


def conv_mlp(channels: list[int]) -> nn.Sequential:
    """Pointwise MLP over B x C x N; BatchNorm + ReLU after every layer but the last."""
    layers: list[nn.Module] = []
    for i, (cin, cout) in enumerate(itertools.pairwise(channels)):
        layers.append(nn.Conv1d(cin, cout, 1))
        if i < len(channels) - 2:
            layers += [nn.BatchNorm1d(cout), nn.ReLU()]
    return nn.Sequential(*layers)


class KeypointEncoder(nn.Module):
    def __init__(self, dim: int, hidden: list[int]):
        super().__init__()
        self.encoder = conv_mlp([3, *hidden, dim])

    def forward(self, kpts: torch.Tensor, scores: torch.Tensor) -> torch.Tensor:
        """kpts B x N x 2 (normalised), scores B x N -> B x dim x N."""
        return self.encoder(torch.cat([kpts.transpose(1, 2), scores[:, None]], dim=1))


class MultiHeadAttention(nn.Module):
    def __init__(self, heads: int, dim: int):
        super().__init__()
        if dim % heads:
            raise AerolocError(f"attention width {dim} is not a multiple of {heads} heads")
        self.heads = heads
        self.proj = nn.ModuleList([nn.Conv1d(dim, dim, 1) for _ in range(3)])  # query, key, value
        self.merge = nn.Conv1d(dim, dim, 1)

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        b, dim, _ = x.shape
        q, k, v = (p(t).reshape(b, dim // self.heads, self.heads, -1) for p, t in zip(self.proj, (x, source, source)))
        attn = torch.softmax(torch.einsum("bdhn,bdhm->bhnm", q, k) / (dim // self.heads) ** 0.5, dim=-1)
        out = torch.einsum("bhnm,bdhm->bdhn", attn, v)
        return self.merge(out.reshape(b, dim, -1))


class AttentionalPropagation(nn.Module):
    def __init__(self, dim: int, heads: int = 4):
        super().__init__()
        self.attn = MultiHeadAttention(heads, dim)
        self.mlp = conv_mlp([2 * dim, 2 * dim, dim])

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([x, self.attn(x, source)], dim=1))


class AttentionalGNN(nn.Module):
    def __init__(self, dim: int, kinds: list[str]):
        super().__init__()
        self.kinds = list(kinds)
        self.layers = nn.ModuleList([AttentionalPropagation(dim) for _ in self.kinds])

    def forward(self, d0: torch.Tensor, d1: torch.Tensor):
        for layer, kind in zip(self.layers, self.kinds):
            s0, s1 = (d1, d0) if kind == "cross" else (d0, d1)
            d0, d1 = d0 + layer(d0, s0), d1 + layer(d1, s1)
        return d0, d1


def log_optimal_transport(scores: torch.Tensor, dustbin: torch.Tensor, iters: int) -> torch.Tensor:
    """Log-space Sinkhorn on the (M+1) x (N+1) score matrix augmented with dustbins. Row marginals are 1 per
    keypoint and N for the dustbin, columns 1 and M; the result is the log assignment scaled by M + N."""
    b, m, n = scores.shape
    z = torch.cat(
        [
            torch.cat([scores, dustbin.expand(b, m, 1)], 2),
            torch.cat([dustbin.expand(b, 1, n), dustbin.expand(b, 1, 1)], 2),
        ],
        1,
    )
    log_norm = -torch.log(scores.new_tensor(float(m + n)))
    log_mu = torch.cat([log_norm.expand(m), (torch.log(scores.new_tensor(float(n))) + log_norm)[None]])
    log_nu = torch.cat([log_norm.expand(n), (torch.log(scores.new_tensor(float(m))) + log_norm)[None]])
    u = torch.zeros_like(log_mu).expand(b, -1)
    v = torch.zeros_like(log_nu).expand(b, -1)
    for _ in range(iters):
        u = log_mu - torch.logsumexp(z + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(z + u[:, :, None], dim=1)
    return z + u[:, :, None] + v[:, None, :] - log_norm


class SuperGlue(nn.Module):
    """forward(kpts0, scores0, desc0, size0, kpts1, ...) -> (matches0: B x M index into image 1 or -1,
    matching scores B x M). kpts B x N x 2 in pixels, desc B x D x N, size (width, height)."""

    default_conf = {
        "descriptor_dim": 256,
        "keypoint_encoder": [32, 64, 128, 256],
        "n_layers": 9,
        "sinkhorn_iterations": 100,
        "match_threshold": 0.2,
    }

    def __init__(self, conf: dict | None = None):
        super().__init__()
        self.conf = c = merge_conf(self, conf)
        dim = c["descriptor_dim"]
        self.kenc = KeypointEncoder(dim, c["keypoint_encoder"])
        self.gnn = AttentionalGNN(dim, ["self", "cross"] * c["n_layers"])
        self.final_proj = nn.Conv1d(dim, dim, 1)
        self.bin_score = nn.Parameter(torch.tensor(1.0))

    @staticmethod
    def normalise(kpts: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
        """Centre on the image centre, divide by 0.7 x the longer side (SuperGlue's convention)."""
        size = size.to(kpts).reshape(-1, 1, 2)
        return (kpts - size / 2) / (0.7 * size.max(dim=-1, keepdim=True).values)

    def forward(self, kpts0, scores0, desc0, size0, kpts1, scores1, desc1, size1):
        c = self.conf
        d0 = desc0 + self.kenc(self.normalise(kpts0, size0), scores0)
        d1 = desc1 + self.kenc(self.normalise(kpts1, size1), scores1)
        d0, d1 = self.gnn(d0, d1)
        sim = torch.einsum("bdm,bdn->bmn", self.final_proj(d0), self.final_proj(d1)) / c["descriptor_dim"] ** 0.5
        logp = log_optimal_transport(sim, self.bin_score, c["sinkhorn_iterations"])[:, :-1, :-1]
        best0, nn0 = logp.max(dim=2)
        nn1 = logp.argmax(dim=1)
        idx0 = torch.arange(nn0.shape[1], device=nn0.device)[None]
        mutual = nn1.gather(1, nn0) == idx0
        score0 = torch.where(mutual, best0.exp(), torch.zeros_like(best0))
        valid = mutual & (score0 > c["match_threshold"])
        return torch.where(valid, nn0, torch.full_like(nn0, -1)), score0


class SuperGlueMatcher:
    """SuperGlue on SuperPoint features. conf: weights ('outdoor' or 'indoor'), sinkhorn_iterations,
    match_threshold."""

    name = "superglue"
    default_conf = {"weights": "outdoor", "sinkhorn_iterations": 100, "match_threshold": 0.2}

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        self.conf = c = merge_conf(self, conf)
        self.device = to_device(device)
        path = choose_weights(SUPERGLUE_WEIGHTS, c["weights"], f"unknown SuperGlue weights '{c['weights']}'", weights)
        self.net = SuperGlue({"sinkhorn_iterations": c["sinkhorn_iterations"], "match_threshold": c["match_threshold"]})
        load_strict(self.net, load_state_dict(path), path)
        self.net.to(self.device).eval()

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]:
        if len(f0["keypoints"]) == 0 or len(f1["keypoints"]) == 0:
            return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
        d = self.device

        def side(f):
            t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=d)[None]  # noqa: E731
            return t(f["keypoints"]), t(f["scores"]), t(f["descriptors"]).transpose(1, 2), t(f["image_size"])

        with torch.inference_mode():
            m0, s0 = self.net(*side(f0), *side(f1))
        m0, s0 = m0[0].cpu().numpy(), s0[0].cpu().numpy()
        i0 = np.flatnonzero(m0 >= 0)
        return np.stack([i0, m0[i0]], 1).astype(np.int64), s0[i0].astype(np.float32)
