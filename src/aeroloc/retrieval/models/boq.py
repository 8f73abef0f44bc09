"""Bag-of-Queries (Ali-bey et al., CVPR 2024), ResNet50 variant: ResNet50 cut after layer3, a 3x3 conv to
512 channels, two BoQ blocks (transformer encoder + 64 learnt queries read the features by cross-attention),
and a linear layer mixing the 2 x 64 query outputs into 32 rows: 512 x 32 = 16384-d.

Module names follow the authors' torch.hub model (amaralibey/Bag-of-Queries, hubconf.py + src/backbones.py +
src/boq.py): ``backbone.net.{0,1,4,5,6}`` (conv1, bn1, layer1..3 inside one Sequential) and
``aggregator.{proj_c,norm_input,boqs.<i>.*,fc}``. Weights:
https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/resnet50_16384.pth
An intermediate version of the authors' backbone split the ResNet into ``frozen_layers``/``unfrozen_layers``;
checkpoints saved with those names are renamed at load time.
The DINOv2 variant (12288-d) lives elsewhere (it needs a DINOv2 backbone).
"""

from __future__ import annotations

import re

import torch
import torch.nn.functional as F
import torchvision
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource
from aeroloc.retrieval.models.base import GlobalModel, resize_normalize
from aeroloc.retrieval.models.cosplace import as_int

URL = "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/resnet50_16384.pth"


class ResNet50Layer3(nn.Module):
    """torchvision ResNet50 (random init) up to layer3, as one Sequential named ``net``: B x 1024 x H/16 x W/16."""

    def __init__(self):
        super().__init__()
        r = torchvision.models.resnet50(weights=None)
        self.net = nn.Sequential(r.conv1, r.bn1, r.relu, r.maxpool, r.layer1, r.layer2, r.layer3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class BoQBlock(nn.Module):
    """Refine the features (self-attention encoder), then let learnt queries pool them by cross-attention."""

    def __init__(self, in_dim: int, num_queries: int, nheads: int):
        super().__init__()
        self.encoder = nn.TransformerEncoderLayer(
            d_model=in_dim, nhead=nheads, dim_feedforward=4 * in_dim, batch_first=True, dropout=0.0
        )
        self.queries = nn.Parameter(torch.randn(1, num_queries, in_dim))
        self.self_attn = nn.MultiheadAttention(in_dim, num_heads=nheads, batch_first=True)
        self.norm_q = nn.LayerNorm(in_dim)
        self.cross_attn = nn.MultiheadAttention(in_dim, num_heads=nheads, batch_first=True)
        self.norm_out = nn.LayerNorm(in_dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.encoder(x)
        q = self.queries.expand(x.shape[0], -1, -1)
        q = self.norm_q(q + self.self_attn(q, q, q, need_weights=False)[0])
        out = self.norm_out(self.cross_attn(q, x, x, need_weights=False)[0])
        return x, out


class BoQAggregator(nn.Module):
    def __init__(self, in_channels=1024, proj_channels=512, num_queries=64, num_layers=2, row_dim=32):
        super().__init__()
        self.proj_c = nn.Conv2d(in_channels, proj_channels, kernel_size=3, padding=1)
        self.norm_input = nn.LayerNorm(proj_channels)
        self.boqs = nn.ModuleList(
            [BoQBlock(proj_channels, num_queries, nheads=proj_channels // 64) for _ in range(num_layers)]
        )
        self.fc = nn.Linear(num_layers * num_queries, row_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.norm_input(self.proj_c(x).flatten(2).permute(0, 2, 1))  # B x HW x C
        outs = []
        for block in self.boqs:
            x, out = block(x)
            outs.append(out)
        out = self.fc(torch.cat(outs, dim=1).permute(0, 2, 1))  # B x C x row_dim
        return F.normalize(out.flatten(1), p=2, dim=-1)


# the authors' intermediate backbone layout -> the released one
_SPLIT_NAMES = [
    (re.compile(r"^backbone\.frozen_layers\.0\.([01])\."), r"backbone.net.\1."),  # conv1, bn1
    (re.compile(r"^backbone\.frozen_layers\.1\."), "backbone.net.4."),  # layer1
    (re.compile(r"^backbone\.frozen_layers\.2\."), "backbone.net.5."),  # layer2
    (re.compile(r"^backbone\.unfrozen_layers\.0\."), "backbone.net.6."),  # layer3
]


class BoQModel(GlobalModel):
    """BoQ with a ResNet50 backbone trained on GSV-Cities. conf: dim (16384), resize (authors: 384, bicubic)."""

    default_conf = {"backbone": "ResNet50", "dim": 16384, "resize": 384}

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        if self.conf["backbone"] != "ResNet50" or as_int(self.conf["dim"]) != 16384:
            raise AerolocError(
                f"BoQ here has the ResNet50 model with dim 16384 only (got backbone="
                f"{self.conf['backbone']!r}, dim={self.conf['dim']!r}); the DINOv2 variant is "
                "a separate method"
            )
        self.dim = 16384
        self.weight_source = WeightSource(filename="boq_resnet50_16384.pth", url=URL)
        self.backbone = ResNet50Layer3()
        self.aggregator = BoQAggregator(in_channels=1024, proj_channels=512, num_queries=64, num_layers=2, row_dim=32)

    def load_checkpoint(self, state: dict, source="checkpoint") -> None:
        renamed = {}
        for key, value in state.items():
            for pattern, repl in _SPLIT_NAMES:
                key = pattern.sub(repl, key)
            renamed[key] = value
        super().load_checkpoint(renamed, source=source)

    def preprocess(self, image):
        """The authors' README transform: bicubic resize to 384 x 384, ImageNet normalisation."""
        return resize_normalize(image, self.conf["resize"], mode="bicubic")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: B x 3 x H x W (ImageNet-normalised; H, W multiples of 16 ideally) -> B x 16384, unit L2 norm."""
        return self.aggregator(self.backbone(x))
