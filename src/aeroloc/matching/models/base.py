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


# -- helpers shared by the extractors (added with the extractors; the contract above is unchanged) -----------
# Pixel convention: keypoints are in the pixel-EDGE frame (pixel (col, row) covers [col, col+1) x [row, row+1),
# its centre is (col + 0.5, row + 0.5)), the frame aeroloc's homographies and tile georeferences use. Networks
# report pixel-centre indices; each extractor adds 0.5 before calling :func:`finish`.


class Prepared:
    """An image ready for a network: RGB uint8 ``image`` (upscaled), valid-pixel ``mask`` (eroded by the border
    margin) in that frame, ``scale`` = (work width / original width, work height / original height)."""

    def __init__(self, image: np.ndarray, mask: np.ndarray, scale: tuple[float, float], size: tuple[int, int]):
        self.image, self.mask, self.scale, self.size = image, mask, scale, size

    @property
    def valid_fraction(self) -> float:
        return float(self.mask.mean()) if self.mask.size else 0.0


def prepare(
    image: np.ndarray, mask: np.ndarray | None, upscale: float = 1.0, border_px: int = 0, min_side: int = 16
) -> Prepared:
    """Check the input, upscale it and its mask, and erode the mask so no keypoint sits on a black border.

    ``mask`` None means "pixels that are not pure black" (black marks no-data in rendered tiles/orthophotos).
    """
    import cv2

    from aeroloc.core.errors import AerolocError, QueryImageError
    from aeroloc.core.frames import resize

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise QueryImageError(f"local features need an RGB uint8 HxWx3 image, got {image.dtype} {image.shape}")
    h, w = image.shape[:2]
    if mask is None:
        mask = image.max(axis=2) > 0
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise AerolocError(f"valid-pixel mask has shape {mask.shape}, the image is {h}x{w}")
    if not upscale or not np.isfinite(upscale) or upscale <= 0:
        raise AerolocError(f"upscale must be a positive factor, got {upscale}")
    ww, wh = max(1, round(w * upscale)), max(1, round(h * upscale))
    if min(ww, wh) < min_side:
        raise QueryImageError(
            f"image of {w}x{h} px is too small for local features (at least {min_side} px a side "
            f"after upscaling by {upscale})"
        )
    mask = mask.astype(np.uint8)
    if (ww, wh) != (w, h):
        image = resize(image, upscale, enlarge="cubic")
        mask = resize(mask, upscale, nearest=True)
    if border_px > 0 and not mask.all():
        # the outer image edge is not a black border: pad with "valid" so erosion only bites at masked pixels
        k = 2 * int(border_px) + 1
        mask = cv2.erode(mask, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return Prepared(np.ascontiguousarray(image), mask > 0, (ww / w, wh / h), (w, h))


def inner_cap(prep: Prepared, max_keypoints: int, limit: int = 4) -> int:
    """How many keypoints to ask a network for so that ``max_keypoints`` remain after masking."""
    frac = max(prep.valid_fraction, 1.0 / limit)
    return int(np.ceil(max_keypoints / frac * 1.1))


def empty_features(prep: Prepared, dim: int) -> Features:
    return {
        "keypoints": np.zeros((0, 2), np.float32),
        "descriptors": np.zeros((0, dim), np.float32),
        "scores": np.zeros((0,), np.float32),
        "image_size": np.array(prep.size, np.int64),
    }


def finish(
    prep: Prepared, keypoints: np.ndarray, scores: np.ndarray, descriptors: np.ndarray, max_keypoints: int | None
) -> Features:
    """Drop keypoints outside the valid mask, keep the ``max_keypoints`` best, map them to the original frame.

    ``keypoints`` are (N, 2) x, y in the pixel-edge frame of ``prep.image``.
    """
    kp = np.asarray(keypoints, np.float64).reshape(-1, 2)
    scores = np.asarray(scores, np.float32).reshape(-1)
    descriptors = np.asarray(descriptors, np.float32).reshape(len(kp), -1)
    h, w = prep.mask.shape
    col, row = np.floor(kp[:, 0]).astype(np.int64), np.floor(kp[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    keep = np.zeros(len(kp), bool)
    keep[inside] = prep.mask[row[inside], col[inside]]
    order = np.flatnonzero(keep)
    order = order[np.argsort(-scores[order], kind="stable")]
    if max_keypoints is not None and max_keypoints > 0:
        order = order[:max_keypoints]
    sx, sy = prep.scale
    out = kp[order] / np.array([sx, sy])
    return {
        "keypoints": out.astype(np.float32),
        "descriptors": np.ascontiguousarray(descriptors[order]),
        "scores": scores[order],
        "image_size": np.array(prep.size, np.int64),
    }


def load_strict(module, state: dict, source, allow_missing: tuple[str, ...] = (), ignore_unexpected: str = "") -> None:
    """Load ``state`` into ``module``; a readable AerolocError naming ``source`` when keys or shapes differ.

    ``allow_missing``: key suffixes the module computes itself; ``ignore_unexpected``: a regex of checkpoint keys
    known to be unused leftovers.
    """
    import re

    from aeroloc.core.errors import AerolocError

    own = module.state_dict()
    missing = [k for k in own if k not in state and not k.endswith((*allow_missing, "num_batches_tracked"))]
    state = {k: v for k, v in state.items() if k in own or not (ignore_unexpected and re.search(ignore_unexpected, k))}
    unexpected = [k for k in state if k not in own]
    wrong = [k for k in own if k in state and tuple(own[k].shape) != tuple(state[k].shape)]
    if missing or unexpected or wrong:
        raise AerolocError(
            f"{source}: checkpoint does not fit {type(module).__name__} (missing {missing[:3]}, "
            f"unexpected {unexpected[:3]}, wrong shape {wrong[:3]})"
        )
    module.load_state_dict(state, strict=False)


def to_device(device):
    """A torch.device from a device or a name ('auto', 'cpu', 'cuda:0' ...; see aeroloc.core.device)."""
    import torch

    from aeroloc.core.device import pick_device

    return device if isinstance(device, torch.device) else pick_device(device or "cpu")


def merge_conf(owner, conf: dict | None) -> dict:
    """``owner.default_conf`` updated with ``conf``; an unknown key is an error, not a silent no-op."""
    from aeroloc.core.errors import AerolocError

    conf = dict(conf or {})
    bad = sorted(set(conf) - set(owner.default_conf))
    if bad:
        raise AerolocError(f"{owner.name}: unknown option(s) {bad}; known: {', '.join(sorted(owner.default_conf))}")
    return {**owner.default_conf, **conf}


def choose_weights(table: dict, key: str, unknown: str, explicit=None):
    """Resolve the checkpoint ``table[key]`` (see aeroloc.core.weights); ``unknown`` starts the error for a
    key that is not in the table, which then lists the choices."""
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.weights import resolve_weights

    if key not in table:
        raise AerolocError(f"{unknown}; choose one of: {', '.join(sorted(table))}")
    return resolve_weights(table[key], explicit)
