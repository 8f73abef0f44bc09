"""MixVPR (Ali-bey et al., WACV 2023): ResNet50 cut after layer3, then an all-MLP feature mixer.

Module names follow the authors' Lightning ``VPRModel`` (amaralibey/MixVPR, main.py + models/) so their
checkpoints load as saved: ``backbone.model.<torchvision resnet50 names>`` (layer4, avgpool and fc removed)
and ``aggregator.mix.<i>.mix.{0,1,3}`` (LayerNorm, Linear, -, Linear over the 20 x 20 = 400 positions),
``aggregator.channel_proj`` (1024 -> C), ``aggregator.row_proj`` (400 -> R). Descriptor = C x R.
Input is fixed at 320 x 320 (the mixer's width is tied to the 20 x 20 layer3 grid), resized bicubic.

Weights are only on Google Drive (README of amaralibey/MixVPR), which a plain HTTP download cannot fetch,
so ``url`` stays empty and the error names the Drive link and where to put the file.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
import torchvision
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource
from aeroloc.retrieval.models.base import GlobalModel, resize_normalize
from aeroloc.retrieval.models.cosplace import as_int

# dim -> (out_channels, out_rows, Google Drive file id), from the authors' README "Weights" table
VARIANTS = {
    4096: (1024, 4, "1vuz3PvnR7vxnDDLQrdHJaOA04SQrtk5L"),
    512: (256, 2, "1khiTUNzZhfV2UUupZoIsPIbsMRBYVDqj"),
    128: (64, 2, "1DQnefjk1hVICOEYPwE4-CZAZOvi1NSJz"),
}
GRID = 20  # layer3 output side for a 320 x 320 input (stride 16)


class ResNet50Layer3(nn.Module):
    """torchvision ResNet50 (random init) with layer4, avgpool and fc removed; output B x 1024 x H/16 x W/16."""

    def __init__(self):
        super().__init__()
        self.model = torchvision.models.resnet50(weights=None)
        self.model.layer4 = None
        self.model.avgpool = None
        self.model.fc = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = self.model
        x = m.maxpool(m.relu(m.bn1(m.conv1(x))))
        return m.layer3(m.layer2(m.layer1(x)))


class FeatureMixerLayer(nn.Module):
    """Residual MLP across the flattened spatial positions of every channel."""

    def __init__(self, in_dim: int, mlp_ratio: float = 1):
        super().__init__()
        hidden = int(in_dim * mlp_ratio)
        self.mix = nn.Sequential(nn.LayerNorm(in_dim), nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, in_dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.mix(x)


class MixVPRAggregator(nn.Module):
    def __init__(self, in_channels=1024, in_h=GRID, in_w=GRID, out_channels=1024, mix_depth=4, mlp_ratio=1, out_rows=4):
        super().__init__()
        hw = in_h * in_w
        self.mix = nn.Sequential(*[FeatureMixerLayer(hw, mlp_ratio) for _ in range(mix_depth)])
        self.channel_proj = nn.Linear(in_channels, out_channels)
        self.row_proj = nn.Linear(hw, out_rows)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.mix(x.flatten(2))  # B x C x HW
        x = self.channel_proj(x.permute(0, 2, 1)).permute(0, 2, 1)  # B x C' x HW
        x = self.row_proj(x)  # B x C' x R
        return F.normalize(x.flatten(1), p=2, dim=-1)


class MixVPRModel(GlobalModel):
    """MixVPR trained on GSV-Cities. conf: dim (128, 512 or 4096), resize (fixed at 320)."""

    default_conf = {"backbone": "ResNet50", "dim": 4096, "resize": 320}
    checkpoint_key = "state_dict"  # plain state dict (README) or a full Lightning checkpoint: both load

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        dim = as_int(self.conf["dim"])
        if self.conf["backbone"] != "ResNet50" or dim not in VARIANTS:
            raise AerolocError(
                f"MixVPR has trained models only for backbone 'ResNet50' with dim "
                f"{', '.join(map(str, sorted(VARIANTS)))} (got backbone={self.conf['backbone']!r}, "
                f"dim={self.conf['dim']!r})"
            )
        if self.conf["resize"] not in (GRID * 16, (GRID * 16, GRID * 16), [GRID * 16, GRID * 16]):
            raise AerolocError(
                f"MixVPR needs 320 x 320 input (its mixer is sized for a 20 x 20 grid); "
                f"got resize={self.conf['resize']!r}"
            )
        channels, rows, drive_id = VARIANTS[dim]
        self.dim = dim
        self.weight_source = WeightSource(
            filename=f"resnet50_MixVPR_{dim}_channels({channels})_rows({rows}).ckpt",
            note=f"Google Drive only: https://drive.google.com/file/d/{drive_id}/view",
        )
        self.backbone = ResNet50Layer3()
        self.aggregator = MixVPRAggregator(out_channels=channels, out_rows=rows)

    def preprocess(self, image):
        """The authors' demo transform: bicubic resize to 320 x 320, ImageNet normalisation."""
        return resize_normalize(image, self.conf["resize"], mode="bicubic")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: B x 3 x 320 x 320 -> B x dim, unit L2 norm."""
        if tuple(x.shape[-2:]) != (GRID * 16, GRID * 16):
            raise AerolocError(f"MixVPR needs 320 x 320 input, got {tuple(x.shape[-2:])} (use preprocess())")
        return self.aggregator(self.backbone(x))
