"""The contract every global-descriptor method follows.

A method is a ``torch.nn.Module`` with a ``default_conf`` dict (merged with user overrides into ``self.conf``),
a ``dim`` (descriptor length), ``preprocess`` (one RGB uint8 image -> a CHW float tensor of a fixed size so a
batch stacks) and ``forward`` (B x 3 x H x W -> B x dim, L2-normalised). Methods whose parameters are fitted on
the map itself (e.g. a VLAD vocabulary) set ``needs_fit = True`` and implement ``fit(images)``; the fitted
state lives in buffers, so ``state_dict()`` carries it into the database.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
import torch.nn.functional as F

from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import WeightSource, load_state_dict, resolve_weights

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class GlobalModel(torch.nn.Module):
    default_conf: dict = {}
    dim: int = 0
    needs_fit: bool = False
    weight_source: WeightSource | None = None  # None: nothing to download (e.g. fitted on the map)
    checkpoint_key: str | None = None  # nested key of the checkpoint holding the state dict, if any

    def __init__(self, conf: dict | None = None):
        super().__init__()
        self.conf = {**self.default_conf, **(conf or {})}

    # -- weights ------------------------------------------------------------------------------------
    def load_weights(self, explicit=None) -> None:
        """Find the checkpoint (see :mod:`aeroloc.core.weights`) and load it strictly."""
        if self.weight_source is None and explicit is None:
            return
        path = (
            resolve_weights(self.weight_source, explicit)
            if self.weight_source
            else resolve_weights(WeightSource(filename=str(explicit)), explicit)
        )
        self.load_checkpoint(load_state_dict(path, key=self.checkpoint_key), source=path)

    def load_checkpoint(self, state: dict, source="checkpoint") -> None:
        """Strict load with a readable error (first differing keys/shapes) instead of a torch traceback."""
        own = self.state_dict()
        # BatchNorm step counters are bookkeeping, absent from some published checkpoints: keep ours
        missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
        state = {**{k: v for k, v in own.items() if k.endswith("num_batches_tracked")}, **state}
        unexpected = [k for k in state if k not in own]
        wrong = [k for k in own if k in state and tuple(own[k].shape) != tuple(state[k].shape)]
        if missing or unexpected or wrong:
            raise AerolocError(
                f"{source}: checkpoint does not fit {type(self).__name__} "
                f"(missing {missing[:3]}, unexpected {unexpected[:3]}, wrong shape {wrong[:3]})"
            )
        self.load_state_dict(state, strict=True)

    # -- preprocessing ------------------------------------------------------------------------------
    def preprocess(self, image: np.ndarray) -> torch.Tensor:
        """RGB uint8 HxWx3 -> 3 x H' x W' float tensor: resize to conf['resize'] (square side or (h, w)),
        then ImageNet normalisation. Override for other rules."""
        return resize_normalize(image, self.conf.get("resize"), self.conf.get("patch_multiple"))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def fit(self, images: Iterable[np.ndarray]) -> None:  # pragma: no cover - only for needs_fit methods
        raise NotImplementedError


def resize_normalize(image: np.ndarray, size=None, multiple: int | None = None, mode: str = "bilinear") -> torch.Tensor:
    """Resize an RGB uint8 image (antialiased) and apply ImageNet mean/std.

    size: None (keep), an int (square side) or (h, w). multiple: round each side down to a multiple
    (ViTs with patch 14 need it). mode: 'bilinear' or 'bicubic' (what the authors' transform used).
    """
    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float().div_(255.0)
    h, w = t.shape[1:]
    if size is not None:
        h, w = (size, size) if isinstance(size, int) else tuple(size)
    if multiple:
        h, w = max(multiple, h // multiple * multiple), max(multiple, w // multiple * multiple)
    if (h, w) != tuple(t.shape[1:]):
        t = F.interpolate(t[None], size=(h, w), mode=mode, align_corners=False, antialias=True)[0]
        t = t.clamp_(0.0, 1.0)  # bicubic overshoots; PIL (the authors' resize) clips to the pixel range
    mean = torch.tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(3, 1, 1)
    return (t - mean) / std
