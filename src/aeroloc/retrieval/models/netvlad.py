"""NetVLAD (Arandjelović et al., CVPR 2016): VGG16 conv5_3 (before its ReLU) -> NetVLAD with 64 clusters
(32768-d) -> optional PCA-whitening to 4096-d.

Weights are the authors' MatConvNet models converted to MATLAB structs by hloc (the files
gmberton/VPR-methods-evaluation and cvg/Hierarchical-Localization download):
https://cvg-data.inf.ethz.ch/hloc/netvlad/Pitts30K_struct.mat (and TokyoTM_struct.mat). The .mat is read
with scipy and converted at load time, exactly as those projects do: ``net.layers[0..28]`` are the VGG16
layers (conv weights S x S x IN x OUT), ``layers[30]`` holds the NetVLAD soft-assignment weights and the
*negated* cluster centres (both D x K), ``layers[33]`` the whitening (1 x 1 x 32768 x 4096 + bias), and
``net.meta.normalization.averageImage`` the RGB mean subtracted from 0..255 pixels (no std division).
A torch state dict with this module's own key names (e.g. a converted copy) loads too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights
from aeroloc.retrieval.models.base import IMAGENET_MEAN, IMAGENET_STD, GlobalModel, resize_normalize
from aeroloc.retrieval.models.cosplace import as_int, cnn_backbone

MAT_URL = "https://cvg-data.inf.ethz.ch/hloc/netvlad/{name}_struct.mat"
TRAINED_ON = ("Pitts30K", "TokyoTM")
VLAD_LAYER, WHITEN_LAYER = 30, 33  # indices in net.layers of the authors' model
CAFFE_VGG_MEAN = (123.68, 116.779, 103.939)  # placeholder until the checkpoint's averageImage is loaded


class NetVLADLayer(nn.Module):
    """Soft-assign each local descriptor to K centres and sum the residuals: B x D x N -> B x (D*K).

    Keys as in hloc: ``score_proj.weight`` (K x D x 1, no bias) and ``centers`` (D x K).
    """

    def __init__(self, input_dim: int = 512, num_clusters: int = 64):
        super().__init__()
        self.score_proj = nn.Conv1d(input_dim, num_clusters, kernel_size=1, bias=False)
        self.centers = nn.Parameter(torch.empty(input_dim, num_clusters))
        nn.init.xavier_uniform_(self.centers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        assign = F.softmax(self.score_proj(x), dim=1)  # B x K x N
        # sum_n a[k,n] (x[:,n] - c_k), without materialising the B x D x K x N residuals
        vlad = torch.bmm(x, assign.transpose(1, 2)) - self.centers[None] * assign.sum(-1)[:, None, :]
        vlad = F.normalize(vlad, dim=1)  # intra-normalisation (per cluster), as in the MATLAB code
        return F.normalize(vlad.flatten(1), dim=1)  # D-major order: the whitening was learnt on it


class NetVLADModel(GlobalModel):
    """NetVLAD VGG16 (Pitts30K or TokyoTM). conf: dim (4096 whitened, or 32768 raw), weights ('Pitts30K' or
    'TokyoTM'), resize (square side; the authors ran 640 x 480 Pittsburgh images at full size)."""

    default_conf = {"backbone": "VGG16", "dim": 4096, "weights": "Pitts30K", "resize": 480}

    def __init__(self, conf: dict | None = None):
        super().__init__(conf)
        dim, trained_on = as_int(self.conf["dim"]), self.conf["weights"]
        if self.conf["backbone"] != "VGG16" or dim not in (4096, 32768) or trained_on not in TRAINED_ON:
            raise AerolocError(
                f"NetVLAD has VGG16 models with dim 4096 or 32768 and weights "
                f"{' or '.join(TRAINED_ON)} (got backbone={self.conf['backbone']!r}, "
                f"dim={self.conf['dim']!r}, weights={trained_on!r})"
            )
        self.dim = dim
        url = MAT_URL.format(name=trained_on)
        self.weight_source = WeightSource(filename=f"netvlad_{trained_on}_struct.mat", url=url)
        self.backbone = cnn_backbone("VGG16")  # conv5_3 without the ReLU and max-pool after it
        self.netvlad = NetVLADLayer(512, 64)
        if dim == 4096:
            self.whiten = nn.Linear(512 * 64, 4096)
        self.register_buffer("mean", torch.tensor(CAFFE_VGG_MEAN).view(1, 3, 1, 1))

    # -- weights ------------------------------------------------------------------------------------
    def load_weights(self, explicit=None) -> None:
        path = resolve_weights(self.weight_source, explicit)
        if path.suffix.lower() == ".mat":
            conv_indices = [i for i, m in enumerate(self.backbone) if isinstance(m, nn.Conv2d)]
            state = state_from_matconvnet(read_matconvnet(path), conv_indices, hasattr(self, "whiten"), source=path)
        else:
            state = load_state_dict(path)
        self.load_checkpoint(state, source=path)

    # -- inference ----------------------------------------------------------------------------------
    def preprocess(self, image: np.ndarray) -> torch.Tensor:
        """RGB uint8 -> 3 x S x S float RGB in 0..255 (the mean is subtracted in forward, on the device)."""
        t = resize_normalize(image, self.conf["resize"])
        std, mean = torch.tensor(IMAGENET_STD).view(3, 1, 1), torch.tensor(IMAGENET_MEAN).view(3, 1, 1)
        return (t * std + mean).mul_(255.0).clamp_(0.0, 255.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: B x 3 x H x W RGB in 0..255 (see preprocess) -> B x dim, unit L2 norm."""
        feats = self.backbone(x - self.mean)
        feats = F.normalize(feats.flatten(2), dim=1)  # L2 per position before NetVLAD
        desc = self.netvlad(feats)
        if hasattr(self, "whiten"):
            desc = F.normalize(self.whiten(desc), dim=1)
        return desc


def read_matconvnet(path: Path):
    """The ``net`` struct of a MatConvNet .mat file (scipy structs, squeezed like the authors' loader)."""
    try:
        from scipy.io import loadmat
    except ImportError:  # pragma: no cover - scipy is a declared dependency
        raise AerolocError(f"{path}: reading MatConvNet weights needs scipy (pip install scipy)") from None
    try:
        return loadmat(path, struct_as_record=False, squeeze_me=True)["net"]
    except Exception as exc:
        raise AerolocError(f"{path}: not a MatConvNet model file ({type(exc).__name__}: {exc})") from None


def state_from_matconvnet(
    net, conv_indices: list[int], whiten: bool, source="MatConvNet file"
) -> dict[str, torch.Tensor]:
    """Convert the authors' MatConvNet NetVLAD struct to this module's state dict (hloc's conversion)."""
    try:
        layers = net.layers
        state: dict[str, torch.Tensor] = {}
        for i in conv_indices:
            w, b = layers[i].weights[0], layers[i].weights[1]
            w = torch.from_numpy(np.asarray(w, np.float32))  # S x S x IN x OUT
            state[f"backbone.{i}.weight"] = w.permute(3, 2, 0, 1).contiguous()
            state[f"backbone.{i}.bias"] = torch.from_numpy(np.asarray(b, np.float32).reshape(-1))
        score_w, centers = layers[VLAD_LAYER].weights[0], layers[VLAD_LAYER].weights[1]  # both D x K
        score_w = torch.from_numpy(np.asarray(score_w, np.float32))
        state["netvlad.score_proj.weight"] = score_w.T.unsqueeze(-1).contiguous()
        state["netvlad.centers"] = -torch.from_numpy(np.asarray(centers, np.float32))  # stored negated
        if whiten:
            w, b = layers[WHITEN_LAYER].weights[0], layers[WHITEN_LAYER].weights[1]
            w = np.asarray(w, np.float32)
            state["whiten.weight"] = torch.from_numpy(w.reshape(w.shape[-2], w.shape[-1])).T.contiguous()
            state["whiten.bias"] = torch.from_numpy(np.asarray(b, np.float32).reshape(-1))
        mean = np.asarray(net.meta.normalization.averageImage, np.float32).reshape(-1, 3)[0]
        state["mean"] = torch.from_numpy(mean.copy()).view(1, 3, 1, 1)
    except (AttributeError, IndexError, KeyError, TypeError, ValueError) as exc:
        raise AerolocError(
            f"{source}: MatConvNet file does not hold the NetVLAD VGG16 model ({type(exc).__name__}: {exc})"
        ) from None
    return state
