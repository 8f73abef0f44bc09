"""SelaVPR (Lu et al., ICLR 2024; Lu-Feng/SelaVPR): a frozen DINOv2 ViT-L/14 adapted with small adapters.

Global adaptation: every block gets a serial adapter after attention (``adapter1``: x + fc2(relu(fc1(x)))) and a
parallel adapter beside the MLP (``adapter2``, added with weight 0.2), hidden size D/2 (backbone/dinov2/block.py).
Global descriptor: normalised patch tokens -> L2 over channels -> GeM (learned p) -> L2: 1024-d.
Local adaptation (``LocalAdapt``): two stride-2 transposed convolutions upsample the 16 x 16 token map of a
224 x 224 input to a 61 x 61 grid of 128-d features (L2-normalised), matched by mutual nearest neighbours to
re-rank candidates (see ``aeroloc.matching.models.selavpr_local``).

Input: 224 x 224 (their ``--resize 224 224``, ``hard_resize``), ImageNet normalisation.

Weights: the authors' fine-tuned checkpoints on Google Drive (README "Trained Models"): ``SelaVPR_msls.pth``
(MSLS, the default: diverse scenes) or ``SelaVPR_pitts30k.pth`` (``variant="pitts30k"``, urban). They hold the
whole network (DINOv2 + adapters + heads) as ``{"model_state_dict": ...}`` saved from ``nn.DataParallel``, so
keys read ``module.backbone.*``, ``module.aggregation.1.p``, ``module.LocalAdapt.*``; ``checkpoint_key`` picks
the dict and the loader strips ``module.``; the remaining names are this module's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource
from aeroloc.retrieval.models.base import GlobalModel
from aeroloc.retrieval.models.dinov2 import PATCH, Block, DinoV2

_DRIVE = "https://drive.usercontent.google.com/download?export=download&confirm=t&id="
VARIANTS = {  # README "Trained Models": Google-Drive file ids
    "msls": ("SelaVPR_msls.pth", "1vy05l0JTEgr6n8iSoz_P_yjWfEzFPAkV"),
    "pitts30k": ("SelaVPR_pitts30k.pth", "1LKTZZRHfMH3dY3UPagCt2TIlMN5LguGO"),
}


def selavpr_weights(variant: str = "msls") -> WeightSource:
    if variant not in VARIANTS:
        raise AerolocError(f"unknown SelaVPR variant '{variant}'; choose one of: {', '.join(VARIANTS)}")
    filename, drive_id = VARIANTS[variant]
    return WeightSource(
        filename=filename,
        url=_DRIVE + drive_id,
        note=f"SelaVPR fine-tuned on {variant}, Google Drive "
        f"https://drive.google.com/file/d/{drive_id} (linked from Lu-Feng/SelaVPR README)",
    )


class Adapter(nn.Module):
    """Bottleneck MLP (ReLU); with ``skip`` the input is added back (serial adapter)."""

    def __init__(self, dim: int, ratio: float = 0.5, skip: bool = True):
        super().__init__()
        self.skip = skip
        self.D_fc1 = nn.Linear(dim, int(dim * ratio))
        self.D_fc2 = nn.Linear(int(dim * ratio), dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.D_fc2(F.relu(self.D_fc1(x)))
        return x + out if self.skip else out


class AdaptedBlock(Block):
    """DINOv2 block with SelaVPR's serial (``adapter1``) and parallel (``adapter2``, scale 0.2) adapters."""

    PARALLEL_SCALE = 0.2

    def __init__(self, dim: int, num_heads: int, ffn: str = "mlp", mlp_ratio: float = 4.0):
        super().__init__(dim, num_heads, ffn, mlp_ratio)
        self.adapter1 = Adapter(dim, skip=True)
        self.adapter2 = Adapter(dim, skip=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.adapter1(self.attn(self.norm1(x))))
        h = self.norm2(x)
        return x + self.ls2(self.mlp(h) + self.PARALLEL_SCALE * self.adapter2(h))


class ChannelL2Norm(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(x, dim=1)


class GeM(nn.Module):
    """Generalised-mean pooling over H x W with a learned exponent ``p`` (shape (1,), as the checkpoint)."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6):
        super().__init__()
        self.p = nn.Parameter(torch.full((1,), float(p)))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.clamp(min=self.eps).pow(self.p).mean(dim=(-2, -1), keepdim=True).pow(1.0 / self.p)


class Flatten(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, :, 0, 0]


class LocalAdapt(nn.Module):
    """Two 3x3 stride-2 transposed convolutions (padding 1): a g x g token map becomes (4g - 3) x (4g - 3)."""

    def __init__(self, dim: int = 1024):
        super().__init__()
        self.upconv1 = nn.ConvTranspose2d(dim, 256, kernel_size=3, stride=2, padding=1)
        self.upconv2 = nn.ConvTranspose2d(256, 128, kernel_size=3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.upconv2(F.relu(self.upconv1(x)))


def local_grid_to_pixels(index: torch.Tensor | float) -> torch.Tensor | float:
    """Position (continuous pixels of the network input, pixel i spans [i, i+1)) of local-grid cell ``index``.

    Each transposed conv maps input cell i to output cell 2i, so grid cell o sits on patch o/4, whose centre
    is at 14 * o/4 + 7 pixels."""
    return index * (PATCH / 4) + PATCH / 2


class SelaVPR(GlobalModel):
    default_conf = {
        "variant": "msls",  # which released checkpoint: msls or pitts30k
        "resize": 224,
        "patch_multiple": 14,
        "backbone_overrides": None,  # test-only: e.g. {"embed_dim": 64, "num_heads": 2, "depth": 2}
    }
    dim = 1024
    weight_source = selavpr_weights("msls")
    checkpoint_key = "model_state_dict"

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.weight_source = selavpr_weights(self.conf["variant"])
        self.backbone = DinoV2("vitl14", self.conf["backbone_overrides"], block_cls=AdaptedBlock)
        self.aggregation = nn.Sequential(ChannelL2Norm(), GeM(), Flatten())
        self.LocalAdapt = LocalAdapt(self.backbone.embed_dim)
        self.dim = self.backbone.embed_dim

    def token_map(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised patch tokens as B x D x h x w."""
        return self.backbone.feature_map(x)[0]

    def global_from_map(self, fmap: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.aggregation(fmap), dim=-1)

    def local_from_map(self, fmap: torch.Tensor) -> torch.Tensor:
        """Dense local features B x (4h-3) x (4w-3) x 128, unit length (``local_grid_to_pixels`` places them)."""
        return F.normalize(self.LocalAdapt(fmap).permute(0, 2, 3, 1), dim=-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.global_from_map(self.token_map(x))

    def forward_with_local(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(global B x dim, local B x H' x W' x 128) from one backbone pass, as the authors' network returns."""
        fmap = self.token_map(x)
        return self.global_from_map(fmap), self.local_from_map(fmap)
