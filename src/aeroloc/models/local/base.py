"""The contract for local features and matchers.

``Features`` is a plain dict of numpy arrays (so it stores in HDF5 as is):
    keypoints   (N, 2) float32  x, y in the pixel frame of the image given to ``extract``
    descriptors (N, D) float32 (stores may keep float16)
    scores      (N,)   float32
    image_size  (2,)   int64    width, height of that image
An extractor is an object with ``name``, ``conf`` and ``extract(image, mask=None) -> Features`` where image is
RGB uint8 HxWx3 and mask (optional, HxW bool) marks valid pixels (False = black border: no keypoints there).
A matcher has ``name`` and ``match(f0, f1) -> (matches (M, 2) int64 indices into f0/f1, scores (M,) float32)``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

Features = dict[str, np.ndarray]


class Extractor(Protocol):
    name: str
    conf: dict

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features: ...


class Matcher(Protocol):
    name: str

    def match(self, f0: Features, f1: Features) -> tuple[np.ndarray, np.ndarray]: ...
