"""DINOv2 ViT-S/B/L/G with patch 14 (no registers), written to load the official torch.hub checkpoints as is.

Why our own: SALAD, MegaLoc, SelaVPR and AnyLoc all build on ``torch.hub.load('facebookresearch/dinov2', ...)``,
which needs the network and the dinov2 repository at run time. This module reproduces the hub models'
``state_dict`` exactly (names and shapes of ``dinov2/models/vision_transformer.py`` with ``block_chunks=0``,
``img_size=518``, ``init_values=1.0``; ViT-G uses the SwiGLU FFN, ``ffn_layer="swiglufused"``):

    cls_token (1, 1, D)   pos_embed (1, 1 + 37*37 = 1370, D)   mask_token (1, D)
    patch_embed.proj.{weight (D, 3, 14, 14), bias}
    blocks.N.{norm1, attn.qkv (3D, D), attn.proj, ls1.gamma, norm2, mlp.fc1/fc2 | mlp.w12 (2H, D)/w3 (D, H), ls2.gamma}
    norm.{weight, bias}

Inputs of any size whose sides are multiples of 14 work: the 37 x 37 position grid is resized bicubically, with
the official +0.1 offset so the interpolated grid has exactly h x w cells. ``feature_map`` returns normalised
patch tokens; ``value_facet`` returns the value part of one block's attention ``qkv`` (AnyLoc), captured by a
forward hook on that ``qkv`` layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource

PATCH = 14
PRETRAIN_GRID = 37  # img_size 518 / patch 14 in the hub models: pos_embed holds 1 + 37*37 = 1370 rows
DINOV2_URL = "https://dl.fbaipublicfiles.com/dinov2"

# dinov2/models/vision_transformer.py: vit_small/base/large/giant2; hub/backbones.py: ViT-G uses "swiglufused"
ARCHS: dict[str, dict] = {
    "vits14": {"embed_dim": 384, "depth": 12, "num_heads": 6, "ffn": "mlp"},
    "vitb14": {"embed_dim": 768, "depth": 12, "num_heads": 12, "ffn": "mlp"},
    "vitl14": {"embed_dim": 1024, "depth": 24, "num_heads": 16, "ffn": "mlp"},
    "vitg14": {"embed_dim": 1536, "depth": 40, "num_heads": 24, "ffn": "swiglu"},
}


def dinov2_weights(arch: str) -> WeightSource:
    """The official LVD-142M pretrained checkpoint of ``arch`` (hub/backbones.py: <base>/<name>/<name>_pretrain.pth)."""
    if arch not in ARCHS:
        raise AerolocError(f"unknown DINOv2 architecture '{arch}'; choose one of: {', '.join(ARCHS)}")
    name = f"dinov2_{arch}"
    return WeightSource(
        filename=f"{name}_pretrain.pth",
        url=f"{DINOV2_URL}/{name}/{name}_pretrain.pth",
        note=f"official DINOv2 {arch.upper()} checkpoint, as torch.hub 'facebookresearch/dinov2'",
    )


class PatchEmbed(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=PATCH, stride=PATCH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)  # B x (h*w) x D, row-major over the patch grid


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        # channels of qkv are [q | k | v], each split into heads: the layout AnyLoc's value facet relies on
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d_head)) v, as the official code
        return self.proj(out.transpose(1, 2).reshape(b, n, d))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float = 1.0):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class SwiGLU(nn.Module):
    """layers/swiglu_ffn.py SwiGLUFFNFused: hidden = (int(4D * 2/3) + 7) // 8 * 8 (4096 for D = 1536)."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        hidden = (int(hidden * 2 / 3) + 7) // 8 * 8
        self.w12 = nn.Linear(dim, 2 * hidden)
        self.w3 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x1, x2 = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(x1) * x2)


class Block(nn.Module):
    """Pre-norm transformer block with layer scale (layers/block.py, inference path)."""

    def __init__(self, dim: int, num_heads: int, ffn: str = "mlp", mlp_ratio: float = 4.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.ls1 = LayerScale(dim)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = (SwiGLU if ffn == "swiglu" else Mlp)(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoV2(nn.Module):
    """A DINOv2 ViT/14. ``arch`` is one of ARCHS; ``overrides`` (embed_dim, depth, num_heads, ffn) change the
    size (used by users who truncate the network, and by tests that need a tiny model); ``block_cls`` lets a
    method insert its own block (SelaVPR's adapters) while keeping the key layout."""

    def __init__(self, arch: str = "vitb14", overrides: dict | None = None, block_cls: type = Block):
        super().__init__()
        if arch not in ARCHS:
            raise AerolocError(f"unknown DINOv2 architecture '{arch}'; choose one of: {', '.join(ARCHS)}")
        spec = {**ARCHS[arch], **(overrides or {})}
        unknown = set(spec) - set(ARCHS[arch])
        if unknown:
            raise AerolocError(f"unknown DINOv2 size options {sorted(unknown)} (use embed_dim, depth, num_heads, ffn)")
        dim = spec["embed_dim"]
        self.arch, self.embed_dim, self.num_heads = arch, dim, spec["num_heads"]
        self.patch_embed = PatchEmbed(dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + PRETRAIN_GRID**2, dim))
        self.mask_token = nn.Parameter(torch.zeros(1, dim))  # unused at inference, kept for the key layout
        self.blocks = nn.ModuleList(block_cls(dim, spec["num_heads"], spec["ffn"]) for _ in range(spec["depth"]))
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        if self.pos_embed.device.type != "meta":
            nn.init.trunc_normal_(self.pos_embed, std=0.02)  # a usable random init; real weights replace it

    # -- tokens ---------------------------------------------------------------------------------------
    def interpolate_pos_encoding(self, h: int, w: int) -> torch.Tensor:
        """Position embeddings for an h x w patch grid (1 x (1 + h*w) x D), bicubic from the 37 x 37 grid."""
        pos = self.pos_embed
        if h == w == PRETRAIN_GRID:
            return pos
        grid = pos[:, 1:].float().reshape(1, PRETRAIN_GRID, PRETRAIN_GRID, -1).permute(0, 3, 1, 2)
        # the official scale factor (side + 0.1) / 37 guards against float error giving h - 1 cells
        grid = F.interpolate(
            grid,
            scale_factor=((h + 0.1) / PRETRAIN_GRID, (w + 0.1) / PRETRAIN_GRID),
            mode="bicubic",
            align_corners=False,
        )
        if grid.shape[-2:] != (h, w):
            raise AerolocError(f"position-embedding interpolation gave {tuple(grid.shape[-2:])}, expected {(h, w)}")
        grid = grid.permute(0, 2, 3, 1).reshape(1, h * w, -1).to(pos.dtype)
        return torch.cat([pos[:, :1], grid], dim=1)

    def prepare_tokens(self, x: torch.Tensor) -> torch.Tensor:
        """B x 3 x H x W (ImageNet-normalised, sides multiples of 14) -> B x (1 + h*w) x D with positions."""
        h, w = patch_grid(*x.shape[-2:])
        tokens = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), self.patch_embed(x)], dim=1)
        return tokens + self.interpolate_pos_encoding(h, w)

    def tokens(self, x: torch.Tensor, norm: bool = True) -> torch.Tensor:
        """All blocks, then (optionally) the final LayerNorm: B x (1 + h*w) x D (index 0 = CLS)."""
        t = self.prepare_tokens(x)
        for blk in self.blocks:
            t = blk(t)
        return self.norm(t) if norm else t

    def feature_map(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised patch tokens as a B x D x h x w map, and the normalised CLS token B x D."""
        b, _, height, width = x.shape
        t = self.tokens(x)
        fmap = t[:, 1:].reshape(b, height // PATCH, width // PATCH, -1).permute(0, 3, 1, 2)
        return fmap, t[:, 0]

    def value_facet(self, x: torch.Tensor, layer: int) -> torch.Tensor:
        """The value part of block ``layer``'s attention qkv for the patch tokens: B x (h*w) x D (not normalised).

        A forward hook on ``blocks[layer].attn.qkv`` captures its output (as AnyLoc's extractor does); blocks after
        ``layer``, and the rest of block ``layer``, are not run since nothing reads them."""
        if not 0 <= layer < len(self.blocks):
            raise AerolocError(f"DINOv2 layer {layer} out of range (the model has {len(self.blocks)} blocks)")
        captured: dict[str, torch.Tensor] = {}
        target = self.blocks[layer]
        handle = target.attn.qkv.register_forward_hook(lambda mod, inp, out: captured.__setitem__("qkv", out))
        try:
            t = self.prepare_tokens(x)
            for blk in self.blocks[:layer]:
                t = blk(t)
            target.attn.qkv(target.norm1(t))
        finally:
            handle.remove()
        qkv = captured["qkv"]
        d = qkv.shape[-1] // 3
        return qkv[:, 1:, 2 * d :]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The hub model's default output: the normalised CLS token, B x D."""
        return self.tokens(x)[:, 0]


class DinoV2FeatureMap(nn.Module):
    """The backbone wrapper of SALAD and MegaLoc (``models/backbones/dinov2.py``): the hub model sits in
    ``.model`` (hence their key prefix ``backbone.model.``); output = (normalised patch-token map, CLS token)."""

    def __init__(self, arch: str = "vitb14", overrides: dict | None = None):
        super().__init__()
        self.model = DinoV2(arch, overrides)
        self.num_channels = self.model.embed_dim

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.model.feature_map(x)


def patch_grid(height: int, width: int) -> tuple[int, int]:
    """Patch-grid size of an input of height x width pixels (sides must be multiples of 14)."""
    if height % PATCH or width % PATCH:
        raise AerolocError(f"DINOv2 needs image sides that are multiples of {PATCH}, got {height} x {width}")
    return height // PATCH, width // PATCH
