"""Frame-to-frame visual odometry: the similarity (shift, rotation, scale change) between consecutive frames.

A nadir camera over flat ground sees consecutive frames related by a similarity, so ORB keypoints on frames
shrunk to ``side`` px, Hamming matching with Lowe's ratio test and OpenCV's RANSAC similarity
(``estimateAffinePartial2D``) give it in a few milliseconds; the same frame's features serve both of its pairs.
A pair with too few inliers (a black or missing frame, no overlap) gives None: the filter then coasts.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Step:
    A: np.ndarray  # 2x3: current frame px -> previous frame px (full-size pixels)
    inliers: int
    matches: int


@dataclass
class _Features:
    kp: np.ndarray  # N x 2, full-size pixels
    desc: np.ndarray | None


class Odometry:
    def __init__(self, side: int = 320, n_features: int = 800, min_inliers: int = 25, ratio: float = 0.8):
        self.side, self.min_inliers, self.ratio = side, min_inliers, ratio
        self.orb = cv2.ORB_create(n_features, fastThreshold=10)
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.prev: _Features | None = None

    def features(self, image: np.ndarray) -> _Features:
        g = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        k = self.side / max(g.shape[:2])
        small = cv2.resize(g, None, fx=k, fy=k, interpolation=cv2.INTER_AREA) if k < 1 else g
        k = min(k, 1.0)
        kps, desc = self.orb.detectAndCompute(small, None)
        pts = np.array([p.pt for p in kps], np.float32).reshape(-1, 2) / k
        return _Features(pts, desc)

    def reset(self) -> None:
        self.prev = None

    def __call__(self, image: np.ndarray | None) -> Step | None:
        """The step from the previous frame given to this one to ``image``; None for the first frame, a missing
        image, or a pair that doesn't verify. ``image`` None (lost frame) breaks the chain."""
        if image is None:
            self.prev = None
            return None
        cur = self.features(image)
        prev, self.prev = self.prev, cur
        if prev is None or prev.desc is None or cur.desc is None or len(prev.kp) < 8 or len(cur.kp) < 8:
            return None
        pairs = self.matcher.knnMatch(cur.desc, prev.desc, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < self.ratio * m[1].distance]
        if len(good) < self.min_inliers:
            return None
        src = cur.kp[[m.queryIdx for m in good]]
        dst = prev.kp[[m.trainIdx for m in good]]
        A, mask = cv2.estimateAffinePartial2D(
            src,
            dst,
            method=cv2.RANSAC,
            ransacReprojThreshold=3.0 / min(1.0, self.side / max(image.shape[:2])),
            maxIters=500,
            confidence=0.99,
        )
        n = int(mask.sum()) if mask is not None else 0
        if A is None or n < self.min_inliers:
            return None
        return Step(A, n, len(good))
