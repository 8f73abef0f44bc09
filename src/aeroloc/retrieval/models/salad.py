"""DINOv2 SALAD (Izquierdo & Civera, CVPR 2024; serizba/salad): optimal-transport aggregation of DINOv2 tokens.

DINOv2 ViT-B/14 patch tokens (after the final norm) are scored against 64 clusters plus a "dustbin"; a few
Sinkhorn iterations turn the scores into a transport plan; each cluster sums its tokens' 128-d projections
weighted by the plan (then intra-normalised), and a 256-d projection of the CLS token is prepended:
256 + 64 x 128 = 8448-d, L2-normalised. Input 322 x 322 (23 x 23 patches), ImageNet normalisation, as the
authors' ``eval.py --image_size 322 322``.

Weights: the authors' release ``dino_salad.ckpt`` (what their ``hubconf.py`` loads): a flat state dict with
keys ``backbone.model.*`` (the whole DINOv2, fine-tuned) and ``aggregator.*`` -- the names this module uses, so
no conversion. A Lightning checkpoint (their Google-Drive copy) nests the same dict under ``state_dict``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource
from aeroloc.retrieval.models.base import GlobalModel
from aeroloc.retrieval.models.dinov2 import DinoV2FeatureMap

SALAD_WEIGHTS = WeightSource(
    filename="dino_salad.ckpt",
    url="https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt",
    note="DINOv2-B SALAD trained on GSV-Cities, released by the authors (torch.hub serizba/salad)",
)


def log_optimal_transport(scores: torch.Tensor, dustbin: torch.Tensor, iters: int = 3) -> torch.Tensor:
    """Entropic optimal transport of n tokens onto m clusters plus one dustbin row, in log space.

    scores: B x m x n. The dustbin row (score ``dustbin``) absorbs the n - m tokens that clusters cannot take:
    row masses are 1/(m+n) for each cluster and (n-m)/(m+n) for the dustbin, column masses 1/(m+n); the result
    is scaled by (m+n) so each token's column sums to 1. Returns B x (m+1) x n log-probabilities.
    """
    b, m, n = scores.shape
    if n <= m:
        raise AerolocError(f"SALAD needs more image patches ({n}) than clusters ({m}); use a larger input size")
    z = torch.cat([scores, dustbin.to(scores).expand(b, 1, n)], dim=1)
    norm = -math.log(m + n)
    log_rows = torch.full((m + 1,), norm, dtype=scores.dtype, device=scores.device)
    log_rows[-1] = math.log(n - m) + norm
    log_cols = torch.full((n,), norm, dtype=scores.dtype, device=scores.device)
    u = torch.zeros(b, m + 1, dtype=scores.dtype, device=scores.device)
    v = torch.zeros(b, n, dtype=scores.dtype, device=scores.device)
    for _ in range(iters):  # Sinkhorn: alternately match row sums, then column sums
        u = log_rows - torch.logsumexp(z + v[:, None, :], dim=2)
        v = log_cols - torch.logsumexp(z + u[:, :, None], dim=1)
    return z + u[:, :, None] + v[:, None, :] - norm


class SALADAggregator(nn.Module):
    """SALAD head (models/aggregators/salad.py). Sequential indices match the authors' (index 1 is their
    dropout, an identity at inference) so checkpoint keys line up: ``token_features.{0,2}``,
    ``cluster_features.{0,3}``, ``score.{0,3}``, ``dust_bin``."""

    def __init__(
        self,
        num_channels: int = 768,
        num_clusters: int = 64,
        cluster_dim: int = 128,
        token_dim: int = 256,
        mlp_dim: int = 512,
    ):
        super().__init__()
        self.num_clusters, self.cluster_dim, self.token_dim = num_clusters, cluster_dim, token_dim
        self.token_features = nn.Sequential(nn.Linear(num_channels, mlp_dim), nn.ReLU(), nn.Linear(mlp_dim, token_dim))
        self.cluster_features = nn.Sequential(
            nn.Conv2d(num_channels, mlp_dim, 1), nn.Identity(), nn.ReLU(), nn.Conv2d(mlp_dim, cluster_dim, 1)
        )
        self.score = nn.Sequential(
            nn.Conv2d(num_channels, mlp_dim, 1), nn.Identity(), nn.ReLU(), nn.Conv2d(mlp_dim, num_clusters, 1)
        )
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    @property
    def out_dim(self) -> int:
        return self.token_dim + self.num_clusters * self.cluster_dim

    def forward(self, inputs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """(B x C x h x w token map, B x C CLS token) -> B x (token_dim + clusters * cluster_dim), unit norm."""
        fmap, cls = inputs
        feats = self.cluster_features(fmap).flatten(2)  # B x l x n
        plan = log_optimal_transport(self.score(fmap).flatten(2), self.dust_bin).exp()[:, :-1]  # B x m x n
        clusters = torch.einsum("bln,bmn->blm", feats, plan)  # B x l x m (the authors' flatten order)
        desc = torch.cat(
            [F.normalize(self.token_features(cls), dim=-1), F.normalize(clusters, dim=1).flatten(1)], dim=-1
        )
        return F.normalize(desc, dim=-1)


class SALADModel(GlobalModel):
    default_conf = {"resize": 322, "patch_multiple": 14}
    dim = 8448
    weight_source = SALAD_WEIGHTS
    checkpoint_key = "state_dict"  # only present in Lightning checkpoints; the release file is flat

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.backbone = DinoV2FeatureMap("vitb14")
        self.aggregator = SALADAggregator(self.backbone.num_channels, 64, 128, 256)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(x))
