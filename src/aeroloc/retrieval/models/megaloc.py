"""MegaLoc (Berton & Masone, 2025; gmberton/MegaLoc): DINOv2 ViT-B/14 + a SALAD head + a linear projection.

The SALAD head is wider than SALAD's own (64 clusters x 256 + 256 = 16640-d) and a linear layer maps it to
8448-d, followed by L2 normalisation. Trained on a mix of VPR, landmark and indoor data.

Input: the authors' model takes any size and rounds each side to the nearest multiple of 14; to batch tiles we
resize every image to ``resize`` (322 x 322 by default, SALAD's training size; change it in the conf),
ImageNet normalisation.

Weights: ``megaloc.torch`` from the authors' GitHub release (what ``torch.hub.load('gmberton/MegaLoc',
'get_trained_model')`` downloads): a flat state dict with ``backbone.model.*`` (DINOv2) and
``aggregator.agg.*`` / ``aggregator.linear.*`` -- the names this module uses, so no conversion.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from aeroloc.core.weights import WeightSource
from aeroloc.retrieval.models.base import GlobalModel
from aeroloc.retrieval.models.dinov2 import DinoV2FeatureMap
from aeroloc.retrieval.models.salad import SALADAggregator

MEGALOC_WEIGHTS = WeightSource(
    filename="megaloc.torch",
    url="https://github.com/gmberton/MegaLoc/releases/download/v1.0/megaloc.torch",
    note="MegaLoc released by the authors (torch.hub gmberton/MegaLoc)",
)


class MegaLocAggregator(nn.Module):
    """megaloc_model.py ``Aggregator``: SALAD head (``agg``) then ``linear`` to the final size."""

    def __init__(
        self,
        num_channels: int = 768,
        feat_dim: int = 8448,
        num_clusters: int = 64,
        cluster_dim: int = 256,
        token_dim: int = 256,
        mlp_dim: int = 512,
    ):
        super().__init__()
        self.agg = SALADAggregator(num_channels, num_clusters, cluster_dim, token_dim, mlp_dim)
        self.linear = nn.Linear(self.agg.out_dim, feat_dim)

    def forward(self, inputs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        return self.linear(self.agg(inputs))


class MegaLoc(GlobalModel):
    default_conf = {"resize": 322, "patch_multiple": 14}
    dim = 8448
    weight_source = MEGALOC_WEIGHTS

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.backbone = DinoV2FeatureMap("vitb14")
        self.aggregator = MegaLocAggregator(self.backbone.num_channels, self.dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.aggregator(self.backbone(x)), dim=-1)
