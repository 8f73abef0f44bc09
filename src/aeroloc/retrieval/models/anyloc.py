"""AnyLoc-VLAD-DINOv2 (Keetha et al., RA-L 2023; AnyLoc/DINO torch.hub): training-free VPR.

Dense features = the *value* facet of DINOv2 ViT-G/14's attention in block 31 (0-based, of 40), one 1536-d
vector per patch, L2-normalised. They are aggregated by hard-assignment VLAD against a released vocabulary of
32 cluster centres fitted on one "domain" of images (we default to ``aerial``): nearest centre by cosine,
residual to the (unnormalised) centre summed per cluster, intra-normalised, flattened, L2-normalised.

Descriptor dim = num_clusters x 1536 = 32 x 1536 = **49152** (float32: 192 KiB per image; consider PCA or a
compressed Faiss index for large maps).

Weights (two files, both the authors'):
- the official DINOv2 ViT-G/14 checkpoint ``dinov2_vitg14_pretrain.pth`` (1.1 B parameters, 4.5 GB). Only blocks
  0..31 run, so blocks 32..39 are dropped on load (``load_checkpoint``) and never held in memory;
- the vocabulary ``dinov2_vitg14_l31_value_c32_<domain>_c_centers.pt`` (a 32 x 1536 tensor) from the AnyLoc/DINO
  GitHub release (``extra_weight_sources``; ``conf['vocabulary']`` = explicit path).

Input: the authors use full resolution centre-cropped to multiples of 14; to batch tiles we resize to ``resize``
(322 x 322 by default), ImageNet normalisation. ``backbone_overrides`` shrinks the ViT and exists for tests
only (the released files need the default).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights
from aeroloc.retrieval.models.base import GlobalModel
from aeroloc.retrieval.models.dinov2 import ARCHS, DinoV2, dinov2_weights

ANYLOC_RELEASE = "https://github.com/AnyLoc/DINO/releases/download/v1"
DOMAINS = ("indoor", "urban", "aerial", "structured", "unstructured", "global")  # hubconf.py AVAIL_VLADCC_FILES


def vocabulary_weights(domain: str = "aerial", layer: int = 31, num_clusters: int = 32) -> WeightSource:
    """The released VLAD cluster centres for ViT-G/14, value facet (hubconf.py naming)."""
    if domain not in DOMAINS:
        raise AerolocError(f"unknown AnyLoc domain '{domain}'; choose one of: {', '.join(DOMAINS)}")
    name = f"dinov2_vitg14_l{layer}_value_c{num_clusters}_{domain}_c_centers.pt"
    return WeightSource(
        filename=name, url=f"{ANYLOC_RELEASE}/{name}", note=f"AnyLoc VLAD vocabulary, domain '{domain}'"
    )


def hard_vlad(desc: torch.Tensor, centers: torch.Tensor) -> torch.Tensor:
    """VLAD with hard assignment, as AnyLoc's ``VLAD.generate``.

    desc: B x N x D unit-length local descriptors; centers: C x D. Assignment by cosine similarity; residuals to
    the raw centres; per-cluster L2 (empty clusters stay zero), flatten (cluster-major), global L2 -> B x C*D.
    """
    n_clusters = centers.shape[0]
    labels = (desc @ F.normalize(centers, dim=1).T).argmax(dim=-1)  # B x N
    assign = F.one_hot(labels, n_clusters).to(desc.dtype)  # B x N x C
    residual_sums = torch.einsum("bnc,bnd->bcd", assign, desc) - assign.sum(1)[..., None] * centers[None]
    return F.normalize(F.normalize(residual_sums, dim=2).flatten(1), dim=1)


def load_vocabulary(path, shape: tuple[int, int]) -> torch.Tensor:
    """Read a saved C x D tensor of cluster centres (the AnyLoc release files hold a bare tensor)."""
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise AerolocError(f"{path}: not a readable vocabulary file ({type(exc).__name__}: {exc})") from None
    if isinstance(obj, dict):
        obj = obj.get("c_centers", obj.get("centroids"))
    if not isinstance(obj, torch.Tensor) or tuple(obj.shape) != tuple(shape):
        found = tuple(obj.shape) if isinstance(obj, torch.Tensor) else type(obj).__name__
        raise AerolocError(f"{path}: expected cluster centres of shape {tuple(shape)}, found {found}")
    return obj.float()


class AnyLoc(GlobalModel):
    default_conf = {
        "domain": "aerial",  # vocabulary: indoor, urban, aerial, structured, unstructured, global
        "layer": 31,  # block whose value facet is used (released vocabularies: 31)
        "num_clusters": 32,  # released vocabularies: 32
        "resize": 322,
        "patch_multiple": 14,
        "vocabulary": None,  # explicit path to the c_centers.pt file
        "backbone_overrides": None,  # test-only: e.g. {"embed_dim": 64, "num_heads": 2, "depth": 3}
    }
    dim = 32 * 1536  # 49152
    weight_source = dinov2_weights("vitg14")
    extra_weight_sources = (vocabulary_weights("aerial"),)

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        c = self.conf
        overrides = dict(c["backbone_overrides"] or {})
        full_depth = overrides.get("depth", ARCHS["vitg14"]["depth"])
        self.layer = int(c["layer"])
        if not 0 <= self.layer < full_depth:
            raise AerolocError(f"AnyLoc layer {self.layer} out of range (ViT-G/14 has {full_depth} blocks)")
        self.full_depth = full_depth
        overrides["depth"] = self.layer + 1  # later blocks are never run
        self.backbone = DinoV2("vitg14", overrides)
        self.vocabulary_source = vocabulary_weights(c["domain"], self.layer, int(c["num_clusters"]))
        self.register_buffer("c_centers", torch.zeros(int(c["num_clusters"]), self.backbone.embed_dim))
        self.dim = int(c["num_clusters"]) * self.backbone.embed_dim

    def load_weights(self, explicit=None) -> None:
        """DINOv2 ViT-G checkpoint (``explicit`` or the usual search) plus the vocabulary file."""
        path = resolve_weights(self.weight_source, explicit)
        vocab_path = resolve_weights(self.vocabulary_source, self.conf.get("vocabulary"))
        self.load_checkpoint(load_state_dict(path), source=path)
        self.c_centers.copy_(load_vocabulary(vocab_path, tuple(self.c_centers.shape)))

    def load_checkpoint(self, state: dict, source="checkpoint") -> None:
        """Accept our own state dict (with ``c_centers``) or the official DINOv2 file (bare keys, all blocks):
        the latter gets the ``backbone.`` prefix, and its blocks after ``layer`` are dropped."""
        if "c_centers" not in state:
            keep = len(self.backbone.blocks)
            missing_tail = [i for i in range(keep, self.full_depth) if f"blocks.{i}.norm1.weight" not in state]
            if missing_tail:
                raise AerolocError(
                    f"{source}: not a {self.full_depth}-block DINOv2 ViT-G/14 checkpoint (no blocks.{missing_tail[0]})"
                )
            state = {
                f"backbone.{k}": v
                for k, v in state.items()
                if not (k.startswith("blocks.") and int(k.split(".")[1]) >= keep)
            }
            state["c_centers"] = self.c_centers
        super().load_checkpoint(state, source)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        values = F.normalize(self.backbone.value_facet(x, self.layer), dim=-1)  # B x N x D
        return hard_vlad(values, self.c_centers)
