"""On-disk stores that survive interruption.

- :class:`DescriptorStore`: an (n, dim) float16 ``.npy`` memmap filled in order; ``progress.json`` records how
  many rows are final (written after the rows are flushed), ``meta.json`` with ``complete: true`` is written
  last. A half-written store resumes from its last flushed row and is never read as complete.
- :class:`FeatureStore`: local features per tile in HDF5, one group per tile; a group exists only once fully
  written (written under a temporary name, then renamed). Encodings (format :data:`FEATURE_FORMAT`) are chosen
  to keep a tile of the default re-ranker (XFeat, 2048 x 64-d) under 200 KB: see :meth:`FeatureStore.encode`.
Both are keyed by a hash of their configuration (:func:`config_key`), so a changed configuration never reuses
stale data.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from aeroloc.errors import AerolocError


def config_key(*parts) -> str:
    """A short stable hash of JSON-able parts (method conf, weights identity, tile database hash …)."""
    blob = json.dumps(parts, sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:12]


def file_identity(path) -> str:
    """Cheap identity of a file for cache keys: size + first/last MiB digest."""
    path = Path(path)
    h = hashlib.sha1(str(path.stat().st_size).encode())
    with open(path, "rb") as f:
        h.update(f.read(1 << 20))
        f.seek(max(0, path.stat().st_size - (1 << 20)))
        h.update(f.read(1 << 20))
    return h.hexdigest()[:16]


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(obj, indent=1, default=str))
    os.replace(tmp, path)


class DescriptorStore:
    def __init__(self, folder, n: int, dim: int, meta: dict | None = None):
        self.folder = Path(folder)
        self.n, self.dim = n, dim
        self.meta = meta or {}
        self.path = self.folder / "descriptors.npy"
        self.progress_path = self.folder / "progress.json"
        self.meta_path = self.folder / "meta.json"

    @classmethod
    def open_complete(cls, folder) -> "DescriptorStore":
        folder = Path(folder)
        meta_path = folder / "meta.json"
        if not meta_path.is_file():
            raise AerolocError(f"{folder}: descriptor store missing or incomplete (rebuild with 'aeroloc build')")
        meta = json.loads(meta_path.read_text())
        if not meta.get("complete"):
            raise AerolocError(f"{folder}: descriptor store incomplete (rerun 'aeroloc build' to resume)")
        return cls(folder, meta["n"], meta["dim"], meta)

    @property
    def complete(self) -> bool:
        if not self.meta_path.is_file():
            return False
        m = json.loads(self.meta_path.read_text())
        return bool(m.get("complete")) and m.get("n") == self.n and m.get("dim") == self.dim

    def done(self) -> int:
        """Rows already final (0 for a new store, or after a shape change)."""
        if self.complete:
            return self.n
        if not (self.path.is_file() and self.progress_path.is_file()):
            return 0
        p = json.loads(self.progress_path.read_text())
        if p.get("n") != self.n or p.get("dim") != self.dim:
            return 0
        return int(p.get("done", 0))

    def _memmap(self, mode):
        return np.lib.format.open_memmap(self.path, mode=mode, dtype=np.float16, shape=(self.n, self.dim))

    def writer(self):
        """Open for appending: returns (start_row, write(rows) callable, finish() callable)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        start = self.done()
        if start == 0 or not self.path.is_file():
            start = 0
            mm = self._memmap("w+")
        else:
            mm = self._memmap("r+")
        state = {"i": start}

        def write(rows: np.ndarray) -> None:
            rows = np.asarray(rows)
            if rows.ndim != 2 or rows.shape[1] != self.dim:
                raise AerolocError(f"descriptor shape {rows.shape} does not match the store's dim {self.dim}")
            i = state["i"]
            mm[i:i + len(rows)] = rows.astype(np.float16)
            mm.flush()
            state["i"] = i + len(rows)
            _write_json(self.progress_path, {"n": self.n, "dim": self.dim, "done": state["i"]})

        def finish(extra: dict | None = None) -> None:
            if state["i"] != self.n:
                raise AerolocError(f"{self.folder}: store has {state['i']} of {self.n} rows")
            mm.flush()
            self.meta = {**self.meta, **(extra or {}), "n": self.n, "dim": self.dim, "dtype": "float16",
                         "complete": True}
            _write_json(self.meta_path, self.meta)
            self.progress_path.unlink(missing_ok=True)

        return start, write, finish

    def load(self, mmap: bool = True) -> np.ndarray:
        arr = np.load(self.path, mmap_mode="r" if mmap else None)
        if arr.shape != (self.n, self.dim):
            raise AerolocError(f"{self.path}: shape {arr.shape}, expected {(self.n, self.dim)}")
        return arr

    def bytes_per_item(self) -> float:
        return self.path.stat().st_size / max(1, self.n)


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
            return {k for k in f.keys() if not k.startswith("~")}

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
    def decode(dataset) -> np.ndarray:
        """The stored array back as written (float arrays as float32); format-1 groups have no quant_scale."""
        v = dataset[()]
        scale = dataset.attrs.get("quant_scale")
        if scale is not None:
            return v.astype(np.float32) / np.float32(scale)
        if isinstance(v, np.ndarray) and v.dtype == np.float16:
            return v.astype(np.float32)
        return v

    def write_many(self, items: dict[str, dict]) -> None:
        with self._open("a") as f:
            for name, feats in items.items():
                tmp = "~" + name
                if tmp in f:
                    del f[tmp]
                g = f.create_group(tmp)
                for k, v in feats.items():
                    v, attrs = self.encode(k, v)
                    ds = g.create_dataset(k, data=v)
                    ds.attrs.update(attrs)
                if name in f:
                    del f[name]
                f.move(tmp, name)
            f.flush()

    def reader(self):
        """Context manager yielding ``get(name) -> Features`` (float arrays back as float32, see ``decode``)."""
        store = self

        class _Reader:
            def __enter__(self):
                self.f = store._open("r")
                return self

            def __exit__(self, *exc):
                self.f.close()

            def get(self, name: str) -> dict:
                if name not in self.f:
                    raise AerolocError(f"{store.path}: no features for tile {name}")
                g = self.f[name]
                return {k: store.decode(g[k]) for k in g.keys()}

        return _Reader()

    def bytes_per_item(self) -> float:
        """Bytes on disk per stored tile: the whole file (HDF5 metadata, leftovers of interrupted writes) / tiles."""
        n = len(self.names())
        return self.path.stat().st_size / n if n else 0.0
