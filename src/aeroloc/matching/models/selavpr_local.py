"""SelaVPR's dense local features and their mutual-nearest-neighbour matching (Lu et al., ICLR 2024).

SelaVPR re-ranks retrieval candidates by the number of mutual nearest neighbours between the two images'
dense 128-d local features, without spatial verification (``local_matching.py``). Here the features become
keypoints so any re-ranker (inlier counting, homography) can use them:

- ``SelaVPRLocal.extract``: the image is resized to the network input (224 x 224), the local-adaptation head
  gives a (4g - 3)^2 grid (61 x 61 = 3721 features for 224 px); cell o of the grid sits at 14 * o/4 + 7 input
  pixels (``local_grid_to_pixels``), scaled back to the given image. Keypoints use pixel-index coordinates
  (the centre of pixel (0, 0) is (0, 0)). Cells whose pixel is masked out are dropped. Scores are 1: the
  features carry no confidence.
- ``SelaVPRMutualNN.match``: cosine similarity, keep pairs that are each other's best match (optionally above
  ``min_similarity``); the score is the similarity.
"""

from __future__ import annotations

import numpy as np
import torch

from aeroloc.core.errors import AerolocError
from aeroloc.matching.models.base import Features


class SelaVPRLocal:
    """Extractor over a SelaVPR network: ``model`` (a loaded ``SelaVPR``) or built from ``conf`` via the
    retrieval registry (``conf['weights']`` = explicit checkpoint, ``conf['model']`` = SelaVPR conf)."""

    name = "selavpr-local"
    default_conf = {"model": {}, "weights": None, "device": "cpu"}

    def __init__(self, conf: dict | None = None, model=None):
        self.conf = {**self.default_conf, **(conf or {})}
        if model is None:
            from aeroloc.retrieval.models import build_method

            model = build_method(
                "selavpr", self.conf["model"], weights=self.conf["weights"], device=self.conf["device"]
            )
        self.model = model.eval()
        self.device = next(model.parameters()).device

    def dense(self, image: np.ndarray) -> tuple[torch.Tensor, tuple[int, int]]:
        """Local features (H' x W' x 128 tensor on the CPU) and the (height, width) of the network input."""
        x = self.model.preprocess(image)[None].to(self.device)
        with torch.inference_mode():
            local = self.model.local_from_map(self.model.token_map(x))[0]
        return local.float().cpu(), tuple(x.shape[-2:])

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        from aeroloc.retrieval.models.selavpr import local_grid_to_pixels

        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise AerolocError(
                f"SelaVPR local features need an RGB uint8 H x W x 3 image, got {image.dtype} {image.shape}"
            )
        height, width = image.shape[:2]
        local, (in_h, in_w) = self.dense(image)
        gh, gw, dim = local.shape
        ys, xs = np.meshgrid(np.arange(gh, dtype=np.float64), np.arange(gw, dtype=np.float64), indexing="ij")
        # input-pixel continuous position -> given-image continuous position -> pixel-index coordinates
        kx = local_grid_to_pixels(xs.ravel()) * (width / in_w) - 0.5
        ky = local_grid_to_pixels(ys.ravel()) * (height / in_h) - 0.5
        keypoints = np.stack([kx, ky], axis=1).astype(np.float32)
        descriptors = local.reshape(-1, dim).numpy().astype(np.float32)
        if mask is not None:
            if mask.shape != (height, width):
                raise AerolocError(f"mask shape {mask.shape} differs from the image's {(height, width)}")
            cols = np.clip(np.rint(kx), 0, width - 1).astype(int)
            rows = np.clip(np.rint(ky), 0, height - 1).astype(int)
            keep = mask[rows, cols].astype(bool)
            keypoints, descriptors = keypoints[keep], descriptors[keep]
        return {
            "keypoints": keypoints,
            "descriptors": descriptors,
            "scores": np.ones(len(keypoints), dtype=np.float32),
            "image_size": np.array([width, height], dtype=np.int64),
        }


class SelaVPRMutualNN:
    """Mutual nearest neighbours by cosine similarity (descriptors are unit length)."""

    name = "selavpr-mnn"
    default_conf = {"min_similarity": None}

    def __init__(self, conf: dict | None = None):
        self.conf = {**self.default_conf, **(conf or {})}

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]:
        d0 = torch.from_numpy(np.asarray(f0["descriptors"], dtype=np.float32))
        d1 = torch.from_numpy(np.asarray(f1["descriptors"], dtype=np.float32))
        if len(d0) == 0 or len(d1) == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        if d0.shape[1] != d1.shape[1]:
            raise AerolocError(
                f"descriptor sizes differ ({d0.shape[1]} vs {d1.shape[1]}): features of different "
                "extractors cannot be matched"
            )
        sim = d0 @ d1.T
        best1 = sim.argmax(dim=1)  # for each f0 feature, its best f1 feature
        best0 = sim.argmax(dim=0)  # for each f1 feature, its best f0 feature
        idx0 = torch.arange(len(d0))
        mutual = best0[best1] == idx0
        scores = sim[idx0, best1]
        if self.conf["min_similarity"] is not None:
            mutual &= scores >= float(self.conf["min_similarity"])
        matches = torch.stack([idx0[mutual], best1[mutual]], dim=1)
        return matches.numpy().astype(np.int64), scores[mutual].numpy().astype(np.float32)
