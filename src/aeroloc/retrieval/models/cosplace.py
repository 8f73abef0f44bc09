"""CosPlace (Berton et al., CVPR 2022): a torchvision CNN, then L2 -> GeM -> FC -> L2.

Our module mirrors the authors' ``GeoLocalizationNet`` (gmberton/CosPlace, cosplace_model/cosplace_network.py)
so their release checkpoints load without renaming: ``backbone.<i>`` is the ResNet without avgpool/fc (or
VGG16 ``features`` without the last ReLU + max-pool), ``aggregation`` = [L2Norm, GeM, Flatten, Linear, L2Norm],
hence ``aggregation.1.p`` (GeM exponent) and ``aggregation.3.weight`` (the FC).
Weights: ``https://github.com/gmberton/CosPlace/releases/download/v1.0/{backbone}_{dim}_cosplace.pth`` (the
URL its hubconf.py ``get_trained_model`` downloads), for the (backbone, dim) pairs in ``AVAILABLE``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
import torchvision
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource
from aeroloc.retrieval.models.base import GlobalModel

# channels of the last conv layer (the GeM input), as in the authors' CHANNELS_NUM_IN_LAST_CONV
LAST_CONV_CHANNELS = {"ResNet18": 512, "ResNet50": 2048, "ResNet101": 2048, "ResNet152": 2048, "VGG16": 512}


class L2Norm(nn.Module):
    def __init__(self, dim: int = 1):
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(x, p=2.0, dim=self.dim)


class GeM(nn.Module):
    """Generalised-mean pooling with a learnt exponent p (one scalar, stored as ``p`` of shape [1])."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6):
        super().__init__()
        self.p = nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), x.shape[-2:]).pow(1.0 / self.p)


class Flatten(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, :, 0, 0]


def cnn_backbone(name: str) -> nn.Sequential:
    """A torchvision CNN (random init: never downloads ImageNet weights) cut before global pooling.

    ResNets lose avgpool + fc; VGG16 keeps ``features`` minus its last ReLU and max-pool (GeM then sees
    conv5_3 before the ReLU, as in the authors' code).
    """
    if name.startswith("ResNet"):
        net = getattr(torchvision.models, name.lower())(weights=None)
        return nn.Sequential(*list(net.children())[:-2])
    if name == "VGG16":
        return nn.Sequential(*list(torchvision.models.vgg16(weights=None).features.children())[:-2])
    raise AerolocError(f"unknown CNN backbone '{name}'; choose one of: {', '.join(LAST_CONV_CHANNELS)}")


def as_int(value) -> int | None:
    """A descriptor size given as int or digit string (``--conf dim=512``); None when it is neither."""
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


class CosPlace(GlobalModel):
    """CosPlace trained on SF-XL. conf: backbone (VGG16, ResNet18/50/101/152), dim (see AVAILABLE), resize
    (square side; the authors trained on 512 x 512 crops and tested at full resolution)."""

    default_conf = {"backbone": "ResNet50", "dim": 2048, "resize": 512}
    # backbone -> descriptor sizes with a released checkpoint (authors' hubconf.py AVAILABLE_TRAINED_MODELS)
    AVAILABLE = {
        "VGG16": [64, 128, 256, 512],
        "ResNet18": [32, 64, 128, 256, 512],
        "ResNet50": [32, 64, 128, 256, 512, 1024, 2048],
        "ResNet101": [32, 64, 128, 256, 512, 1024, 2048],
        "ResNet152": [32, 64, 128, 256, 512, 1024, 2048],
    }
    URL = "https://github.com/gmberton/CosPlace/releases/download/v1.0/{backbone}_{dim}_cosplace.pth"
    NAME = "CosPlace"

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        backbone, dim = self.conf["backbone"], as_int(self.conf["dim"])
        if backbone not in self.AVAILABLE or dim not in self.AVAILABLE[backbone]:
            pairs = "; ".join(f"{b}: {', '.join(map(str, d))}" for b, d in self.AVAILABLE.items())
            raise AerolocError(
                f"{self.NAME} has no trained model for backbone={backbone!r} dim={self.conf['dim']!r} "
                f"(available: {pairs})"
            )
        self.dim = dim
        url = self.URL.format(backbone=backbone, dim=dim)
        self.weight_source = WeightSource(filename=url.rsplit("/", 1)[1], url=url)
        self.backbone = cnn_backbone(backbone)
        self.aggregation = nn.Sequential(
            L2Norm(), GeM(), Flatten(), nn.Linear(LAST_CONV_CHANNELS[backbone], dim), L2Norm()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: B x 3 x H x W (ImageNet-normalised) -> B x dim, unit L2 norm."""
        return self.aggregation(self.backbone(x))
