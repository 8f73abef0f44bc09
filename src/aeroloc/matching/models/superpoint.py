"""SuperPoint (DeTone et al., CVPRW 2018): a VGG-style encoder with a keypoint head (65-way softmax per 8x8 cell,
the 65th class meaning "no keypoint") and a descriptor head (256-d per cell, interpolated at keypoints).

Our own implementation; parameter names and shapes equal Magic Leap's ``superpoint_v1.pth`` (from
magicleap/SuperGluePretrainedNetwork, also re-released by cvg/LightGlue), so that checkpoint loads strictly.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights
from aeroloc.matching.models.base import Features, empty_features, finish, load_strict, merge_conf, prepare, to_device

SUPERPOINT_WEIGHTS = WeightSource(
    filename="superpoint_v1.pth",
    url="https://github.com/magicleap/SuperGluePretrainedNetwork/raw/master/models/weights/superpoint_v1.pth",
    note="Magic Leap's SuperPoint (non-commercial licence); cvg/LightGlue's release has the same file",
)

# encoder: (name, in, out); every conv is 3x3, stride 1, padding 1; 2x2 max-pooling after conv1b/2b/3b
_ENCODER = [
    ("conv1a", 1, 64),
    ("conv1b", 64, 64),
    ("conv2a", 64, 64),
    ("conv2b", 64, 64),
    ("conv3a", 64, 128),
    ("conv3b", 128, 128),
    ("conv4a", 128, 128),
    ("conv4b", 128, 128),
]
CELL = 8


class SuperPointNet(nn.Module):
    """Dense SuperPoint: grey B x 1 x H x W in [0, 1] (H, W multiples of 8) -> (keypoint probability
    B x H x W, unit descriptors B x D x H/8 x W/8)."""

    def __init__(self, descriptor_dim: int = 256):
        super().__init__()
        for name, cin, cout in _ENCODER:
            setattr(self, name, nn.Conv2d(cin, cout, 3, padding=1))
        self.convPa = nn.Conv2d(128, 256, 3, padding=1)
        self.convPb = nn.Conv2d(256, CELL * CELL + 1, 1)
        self.convDa = nn.Conv2d(128, 256, 3, padding=1)
        self.convDb = nn.Conv2d(256, descriptor_dim, 1)

    def forward(self, grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = grey
        for name, _, _ in _ENCODER:
            x = F.relu(getattr(self, name)(x))
            if name in ("conv1b", "conv2b", "conv3b"):
                x = F.max_pool2d(x, 2)
        cells = F.softmax(self.convPb(F.relu(self.convPa(x))), dim=1)[:, :-1]  # drop the "no keypoint" bin
        prob = F.pixel_shuffle(cells, CELL)[:, 0]  # channel r*8+c -> row r, column c inside its cell
        desc = F.normalize(self.convDb(F.relu(self.convDa(x))), dim=1)
        return prob, desc


def nms_points(prob: torch.Tensor, radius: int, threshold: float, border: int):
    """Local maxima of an H x W map within (2r+1)^2 windows, above ``threshold`` and ``border`` px from the
    edges -> (rows, cols, scores)."""
    peak = prob == F.max_pool2d(prob[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]
    keep = peak & (prob > threshold)
    if border > 0:
        keep[:border], keep[-border:], keep[:, :border], keep[:, -border:] = False, False, False, False
    rows, cols = torch.nonzero(keep, as_tuple=True)
    return rows, cols, prob[rows, cols]


def sample_cells(desc: torch.Tensor, xy_index: torch.Tensor) -> torch.Tensor:
    """Bilinear descriptors (N x D, unit length) at pixel-index positions; cell j's centre is pixel 8j + 3.5."""
    _, _, hc, wc = desc.shape
    u = (xy_index - (CELL - 1) / 2) / CELL  # position in cell units
    grid = torch.stack([2 * u[:, 0] / max(wc - 1, 1) - 1, 2 * u[:, 1] / max(hc - 1, 1) - 1], dim=-1)
    out = F.grid_sample(desc, grid[None, None], mode="bilinear", align_corners=True)[0, :, 0]
    return F.normalize(out.T, dim=1)


class SuperPointExtractor:
    """conf: max_keypoints, detection_threshold (cvg's LightGlue setting 0.0005; Magic Leap's demo 0.005),
    nms_radius, remove_borders (px of the network input), upscale, border_px."""

    name = "superpoint"
    dim = 256
    default_conf = {
        "max_keypoints": 2048,
        "detection_threshold": 0.0005,
        "nms_radius": 4,
        "remove_borders": 4,
        "upscale": 1.0,
        "border_px": 4,
    }
    weight_source = SUPERPOINT_WEIGHTS

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        self.conf = merge_conf(self, conf)
        self.device = to_device(device)
        path = resolve_weights(self.weight_source, weights)
        self.net = SuperPointNet(self.dim)
        load_strict(self.net, load_state_dict(path), path)
        self.net.to(self.device).eval()

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        c = self.conf
        prep = prepare(image, mask, c["upscale"], c["border_px"], min_side=CELL * 2)
        if not prep.mask.any():
            return empty_features(prep, self.dim)
        h, w = prep.image.shape[:2]
        with torch.inference_mode():
            rgb = torch.tensor(prep.image, device=self.device).permute(2, 0, 1).float() / 255.0
            grey = (rgb * rgb.new_tensor([0.299, 0.587, 0.114])[:, None, None]).sum(0)[None, None]
            pad_h, pad_w = -h % CELL, -w % CELL  # replicate, so padding adds no artificial edge
            grey = F.pad(grey, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else grey
            prob, desc = self.net(grey)
            prob = prob[0, :h, :w]
            rows, cols, scores = nms_points(prob, c["nms_radius"], c["detection_threshold"], c["remove_borders"])
            xy = torch.stack([cols, rows], 1).float()
            descriptors = sample_cells(desc, xy)
        kp = xy.cpu().numpy().astype(np.float64) + 0.5  # pixel index -> edge frame
        return finish(prep, kp, scores.cpu().numpy(), descriptors.cpu().numpy(), c["max_keypoints"])
