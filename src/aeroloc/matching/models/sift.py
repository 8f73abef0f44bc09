"""OpenCV SIFT (optionally RootSIFT) with Lowe's ratio test. No weights, rotation invariant, weak across
seasons but a solid same-day baseline (drone photo vs the orthomosaic of the same flight)."""

from __future__ import annotations

import cv2
import numpy as np

from aeroloc.matching.models.base import Features, empty_features, finish, merge_conf, prepare


class SIFTExtractor:
    """conf: max_keypoints, contrast_threshold (OpenCV's, lower = more keypoints), edge_threshold, rootsift
    (Hellinger-normalised descriptors: L1-normalise then square root), upscale, border_px."""

    name = "sift"
    dim = 128
    default_conf = {
        "max_keypoints": 4096,
        "contrast_threshold": 0.02,
        "edge_threshold": 10,
        "rootsift": True,
        "upscale": 1.0,
        "border_px": 4,
    }

    def __init__(self, conf: dict | None = None, device="cpu"):
        self.conf = merge_conf(self, conf)
        self.sift = cv2.SIFT_create(
            nfeatures=0, contrastThreshold=self.conf["contrast_threshold"], edgeThreshold=self.conf["edge_threshold"]
        )

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        c = self.conf
        prep = prepare(image, mask, c["upscale"], c["border_px"])
        if not prep.mask.any():
            return empty_features(prep, self.dim)
        grey = cv2.cvtColor(prep.image, cv2.COLOR_RGB2GRAY)
        kps, desc = self.sift.detectAndCompute(grey, prep.mask.astype(np.uint8) * 255)
        if desc is None or not kps:
            return empty_features(prep, self.dim)
        desc = desc.astype(np.float32)
        if c["rootsift"]:
            desc = np.sqrt(desc / (desc.sum(axis=1, keepdims=True) + 1e-8))
        else:
            desc /= np.linalg.norm(desc, axis=1, keepdims=True) + 1e-8
        kp = np.array([k.pt for k in kps], np.float64) + 0.5  # OpenCV: pixel centre at integer coordinates
        scores = np.array([k.response for k in kps], np.float32)
        return finish(prep, kp, scores, desc, c["max_keypoints"])


class RatioTestMatcher:
    """Nearest neighbour accepted when it is clearly closer than the second (distance ratio < ``ratio``);
    ``mutual`` additionally requires the match to be the nearest neighbour in the other direction too."""

    name = "ratio"
    default_conf = {"ratio": 0.8, "mutual": True}

    def __init__(self, conf: dict | None = None, device="cpu"):
        self.conf = merge_conf(self, conf)
        self.bf = cv2.BFMatcher(cv2.NORM_L2)

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]:
        d0 = np.ascontiguousarray(f0["descriptors"], np.float32)
        d1 = np.ascontiguousarray(f1["descriptors"], np.float32)
        none = np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
        if len(d0) < 2 or len(d1) < 2:
            return none
        knn = self.bf.knnMatch(d0, d1, k=2)
        pairs, scores = [], []
        for m in knn:
            if len(m) == 2 and m[0].distance < self.conf["ratio"] * m[1].distance:
                pairs.append((m[0].queryIdx, m[0].trainIdx))
                scores.append(1.0 - m[0].distance / max(m[1].distance, 1e-8))
        if not pairs:
            return none
        pairs, scores = np.array(pairs, np.int64), np.array(scores, np.float32)
        if self.conf["mutual"]:
            back = np.full(len(d1), -1, np.int64)
            for m in self.bf.match(d1, d0):
                back[m.queryIdx] = m.trainIdx
            keep = back[pairs[:, 1]] == pairs[:, 0]
            pairs, scores = pairs[keep], scores[keep]
        return pairs, scores
