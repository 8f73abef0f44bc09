"""Global descriptors per shard (``GDIR/shards/NNNNN.npy``, float16) and their merge into the one store.

The merge appends the shards in order to ``descriptors.npy`` with plain file writes (no memory map held open:
RAM stays flat in the map size) and renames it into place, so the store is complete or absent.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_path
from aeroloc.retrieval.shards import Shard, is_complete, mark_complete, write_shard_file


@dataclass(frozen=True)
class GlobalTask:
    """Describe a shard's tiles with ``method`` (fitted state ``folder/model.pt`` when it has one) in batches
    of ``batch_size`` from the shard start."""

    method: str
    conf: dict
    weights: str | None
    folder: Path
    batch_size: int = 16

    def open(self):
        import torch

        from aeroloc.retrieval.models import build_method

        model = build_method(self.method, self.conf, self.weights, device="cpu")
        state = self.state_path()
        if state.is_file():
            model.load_state_dict(torch.load(state, map_location="cpu", weights_only=True), strict=True)
        return model.eval()

    def state_path(self) -> Path:
        """The method's fitted state (its vocabulary), when it has one."""
        return self.folder / "model.pt"

    def run(self, model, shard: Shard, images: list[np.ndarray], ids: list[str]) -> None:
        out = describe(model, images, self.batch_size)
        path = self.folder / "shards" / f"{shard.name}.npy"
        write_shard_file(path, lambda tmp: _save_npy(tmp, out))
        mark_complete(self.folder, shard, {"dim": int(out.shape[1])})


@dataclass(frozen=True)
class TurnedGlobalTask(GlobalTask):
    """The shard's tiles described at the seven other turns (:data:`~aeroloc.core.frames.TILE_TURNS`), rows
    tile-major (tile i at turn k: row ``i * 7 + k - 1``), each view the map turned about the tile's centre
    (:func:`~aeroloc.maps.windows.turned_windows`): a photo of unknown heading is then searched upright against
    every (tile, turn) with its one descriptor (aeroloc.retrieval.retriever)."""

    def state_path(self) -> Path:
        return self.folder.parent / "model.pt"  # the upright descriptors' folder: one vocabulary for both

    def read(self, source, shard: Shard) -> list[np.ndarray]:
        from aeroloc.core.frames import TILE_TURNS, rotation_angle
        from aeroloc.maps.windows import turned_windows

        angles = [rotation_angle(k) for k in TILE_TURNS]
        return list(turned_windows(source.map(), source.tiles[shard.start : shard.stop], angles))


def _save_npy(tmp: Path, arr: np.ndarray) -> None:
    with open(tmp, "wb") as f:
        np.save(f, arr)


def describe(model, images: list[np.ndarray], batch_size: int) -> np.ndarray:
    """(n, dim) float16 descriptors of ``images`` in batches of ``batch_size`` (CPU, inference mode)."""
    import torch

    rows = []
    with torch.inference_mode():
        for s in range(0, len(images), batch_size):
            x = torch.stack([model.preprocess(im) for im in images[s : s + batch_size]])
            rows.append(model(x).float().numpy().astype(np.float16))
    return np.concatenate(rows) if rows else np.zeros((0, model.dim), np.float16)


def merge(folder: Path, shards: list[Shard], n: int, dim: int, rows_per_tile: int = 1) -> Path:
    """Concatenate the complete shards into ``folder/descriptors.npy`` (atomically; ``n`` rows, ``rows_per_tile``
    a tile); returns its path."""
    dest = folder / "descriptors.npy"
    with atomic_path(dest) as tmp, open(tmp, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float16)), "fortran_order": False, "shape": (n, dim)}
        )
        for shard in shards:
            if not is_complete(folder, shard):
                raise AerolocError(f"{folder}: shard {shard.name} is not complete; rerun 'aeroloc build' to resume")
            arr = np.load(folder / "shards" / f"{shard.name}.npy")
            want = (len(shard) * rows_per_tile, dim)
            if arr.shape != want or arr.dtype != np.float16:
                raise AerolocError(f"{folder}: shard {shard.name} has shape {arr.shape}, expected {want}")
            f.write(np.ascontiguousarray(arr).tobytes())
    return dest


__all__ = ["GlobalTask", "TurnedGlobalTask", "describe", "merge"]
