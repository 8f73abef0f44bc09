"""The local-feature store: features per tile in HDF5, one group per tile, surviving interruption.

A group exists only once fully written (written under a temporary name, then renamed). Encodings (format
:data:`FEATURE_FORMAT`) keep a tile of the default re-ranker (XFeat, 2048 x 64-d) under 200 KB: see
:meth:`FeatureStore.encode`. Keyed by a hash of its configuration (:func:`aeroloc.core.io.config_key`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError

# Version of the FeatureStore encoding; part of the store's directory key (localfeatures.local_key) so a store
# written in another format is never mixed with this one. 1: float16 descriptors; 2: int8 unit-norm descriptors.
FEATURE_FORMAT = 2
QUANT_SCALE = 127  # int8 descriptors: x_stored = round(x * QUANT_SCALE), read back as x_stored / QUANT_SCALE


class FeatureStore:
    """Local features per tile in one HDF5 file.

    On disk (``encode``): L2-normalised descriptors as int8 (``round(x * 127)``, attribute ``quant_scale``; a
    component of a unit vector is in [-1, 1] so the error is <= 0.5/127), half the bytes of float16, and
    descriptors dominate a tile (XFeat's 2048 x 64: 128 KB instead of 256 KB).
    Other float descriptors (e.g. plain SIFT) and scores stay float16. Keypoints stay float32 (sub-pixel
    positions feed the homographies) unless float16 holds them exactly (XFeat on a 512 px tile: half-pixel
    grid < 1024), which is checked per tile, so it is lossless. Reading gives float32 and also understands
    format-1 groups (float16 descriptors without ``quant_scale``).
    """

    def __init__(self, path):
        self.path = Path(path)

    def _open(self, mode):
        import h5py

        try:
            return h5py.File(self.path, mode)
        except OSError as exc:
            if mode == "a" and self.path.exists():  # a crash mid-write can corrupt HDF5: start afresh
                self.path.unlink()
                return h5py.File(self.path, mode)
            raise AerolocError(f"{self.path}: cannot open feature store ({exc})") from None

    def names(self) -> set[str]:
        if not self.path.is_file():
            return set()
        with self._open("r") as f:
            return {k for k in f if not k.startswith("~")}

    @staticmethod
    def encode(key: str, value) -> tuple[np.ndarray, dict]:
        """(array to store, dataset attributes) for one feature array; see the class docstring."""
        v = np.asarray(value)
        if v.dtype.kind != "f":
            return v, {}
        if key == "descriptors":
            x = v.astype(np.float32)
            norms = np.linalg.norm(x, axis=1) if x.ndim == 2 else np.array([np.nan])
            if np.all(np.abs(norms - 1) <= 1e-2):  # NaN/inf rows fail this and keep float16
                q = np.clip(np.rint(x * QUANT_SCALE), -QUANT_SCALE, QUANT_SCALE).astype(np.int8)
                return q, {"quant_scale": QUANT_SCALE}
            return v.astype(np.float16), {}
        if key == "scores":
            return v.astype(np.float16), {}
        if key == "keypoints" and v.dtype != np.float16:
            h = v.astype(np.float16)
            if np.array_equal(h.astype(v.dtype), v):  # lossless (NaN never compares equal: stays as is)
                return h, {}
        return v, {}

    @staticmethod
    def read_group(f, name: str, where) -> dict:
        """The features of group ``name`` of the open file ``f`` (of the store at ``where``, for the error), each
        array back as written (float arrays as float32; int8 descriptors scaled back by their ``quant_scale``,
        which format-1 groups lack). Read through h5py's low-level calls: its high-level objects took 0.57 ms for
        an XFeat tile's 7 arrays (half of it the attribute lookups), these 0.24 ms, and a photo of unknown
        heading reads ~50-250 turned tiles."""
        import h5py

        if name not in f:
            raise AerolocError(f"{where}: no features for tile {name}")
        gid = h5py.h5g.open(f.id, name.encode())
        out = {}
        for key in gid:
            d = h5py.h5d.open(gid, key)
            v = np.empty(d.shape, d.dtype)
            if v.size:
                d.read(h5py.h5s.ALL, h5py.h5s.ALL, v)
            k = key.decode()
            if v.dtype == np.int8 and h5py.h5a.exists(d, b"quant_scale"):
                a = h5py.h5a.open(d, b"quant_scale")
                scale = np.empty(a.shape, a.dtype)
                a.read(scale)
                out[k] = v.astype(np.float32) / np.float32(scale)
            elif v.dtype == np.float16:
                out[k] = v.astype(np.float32)
            else:
                out[k] = v[()] if v.ndim == 0 else v
        return out

    def write_many(self, items: dict[str, dict]) -> None:
        with self._open("a") as f:
            for name, feats in items.items():
                tmp = "~" + name
                if tmp in f:
                    del f[tmp]
                g = f.create_group(tmp)
                for k, v in feats.items():
                    v, attrs = self.encode(k, v)
                    ds = g.create_dataset(k, data=v, track_times=False)  # no clock in the bytes
                    ds.attrs.update(attrs)
                if name in f:
                    del f[name]
                f.move(tmp, name)
            f.flush()

    def reader(self):
        """Context manager yielding ``get(name) -> Features`` (float arrays back as float32, see ``read_group``)."""
        store = self

        class _Reader:
            def __enter__(self):
                self.f = store._open("r")
                return self

            def __exit__(self, *exc):
                self.f.close()

            def get(self, name: str) -> dict:
                return store.read_group(self.f, name, store.path)

        return _Reader()

    def bytes_per_item(self) -> float:
        """Bytes on disk per stored tile: the whole file (HDF5 metadata, leftovers of interrupted writes) / tiles."""
        n = len(self.names())
        return self.path.stat().st_size / n if n else 0.0


class ShardedFeatureStore:
    """The local features of a sharded build: ``FOLDER/shards/NNNNN.h5`` (one :class:`FeatureStore` per shard of
    ``shard_size`` tiles in tiles.csv order, complete once ``NNNNN.done`` exists) + ``extra.h5`` for tiles the
    re-ranker extracted lazily. A query's candidates open only their own shards. A name ``TILE|TURN`` (a turned
    tile, aeroloc.matching.features.turned_name) is kept in TILE's shard.

    Same interface as :class:`FeatureStore` (``names``, ``write_many``, ``reader().get``, ``bytes_per_item``)."""

    def __init__(self, folder, ids: list[str], shard_size: int):
        self.folder = Path(folder)
        self.ids, self.shard_size = ids, shard_size
        self.position = {t: i for i, t in enumerate(ids)}
        self.extra = FeatureStore(self.folder / "extra.h5")
        self.path = self.folder

    def shard_path(self, index: int) -> Path:
        return self.folder / "shards" / f"{index:05d}.h5"

    def _complete(self, index: int) -> bool:
        return (self.folder / "shards" / f"{index:05d}.done").is_file()

    def names(self) -> set[str]:
        n_shards = -(-len(self.ids) // self.shard_size)
        have = set(self.extra.names())
        for k in range(n_shards):
            if self._complete(k):
                have.update(self.ids[k * self.shard_size : (k + 1) * self.shard_size])
        return have

    def write_many(self, items: dict[str, dict]) -> None:
        self.extra.write_many(items)

    def reader(self):
        """Context manager yielding ``get(name)``: the tile's shard file (opened once per reader), else extra.h5."""
        return _ShardedReader(self)

    def bytes_per_item(self) -> float:
        files = list((self.folder / "shards").glob("*.h5")) + [self.extra.path]
        total = sum(p.stat().st_size for p in files if p.is_file())
        n = len(self.names())
        return total / n if n else 0.0


class _ShardedReader:
    def __init__(self, store: ShardedFeatureStore):
        self.store, self.open = store, {}
        self.complete: set[int] = set()  # shards seen finished (one stays finished; an unfinished one is asked again)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for f in self.open.values():
            f.close()

    def _file(self, key, path: Path):
        if key not in self.open:
            self.open[key] = FeatureStore(path)._open("r")
        return self.open[key]

    def get(self, name: str) -> dict:
        s = self.store
        tile = name if name in s.position else name.partition("|")[0]  # "TILE|TURN" lives in TILE's shard
        k = s.position[tile] // s.shard_size if tile in s.position else -1
        if k >= 0 and k not in self.complete and s._complete(k):
            self.complete.add(k)
        if k in self.complete:
            f = self._file(k, s.shard_path(k))
        elif s.extra.path.is_file():
            f = self._file("extra", s.extra.path)
        else:
            raise AerolocError(f"{s.folder}: no features for tile {name}")
        return FeatureStore.read_group(f, name, s.folder)
