"""The global-descriptor store: an (n, dim) float16 ``.npy`` memmap filled in order, surviving interruption.

``progress.json`` records how many rows are final (written after the rows are flushed), ``meta.json`` with
``complete: true`` is written last. A half-written store resumes from its last flushed row and is never read as
complete. Keyed by a hash of its configuration (:func:`aeroloc.core.io.config_key`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import write_json_atomic


class DescriptorStore:
    def __init__(self, folder, n: int, dim: int, meta: dict | None = None):
        self.folder = Path(folder)
        self.n, self.dim = n, dim
        self.meta = meta or {}
        self.path = self.folder / "descriptors.npy"
        self.progress_path = self.folder / "progress.json"
        self.meta_path = self.folder / "meta.json"

    @classmethod
    def open_complete(cls, folder) -> DescriptorStore:
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
            mm[i : i + len(rows)] = rows.astype(np.float16)
            mm.flush()
            state["i"] = i + len(rows)
            write_json_atomic(self.progress_path, {"n": self.n, "dim": self.dim, "done": state["i"]})

        def finish(extra: dict | None = None) -> None:
            if state["i"] != self.n:
                raise AerolocError(f"{self.folder}: store has {state['i']} of {self.n} rows")
            mm.flush()
            self.meta = {
                **self.meta,
                **(extra or {}),
                "n": self.n,
                "dim": self.dim,
                "dtype": "float16",
                "complete": True,
            }
            write_json_atomic(self.meta_path, self.meta)
            self.progress_path.unlink(missing_ok=True)

        return start, write, finish

    def load(self, mmap: bool = True) -> np.ndarray:
        arr = np.load(self.path, mmap_mode="r" if mmap else None)
        if arr.shape != (self.n, self.dim):
            raise AerolocError(f"{self.path}: shape {arr.shape}, expected {(self.n, self.dim)}")
        return arr

    def bytes_per_item(self) -> float:
        return self.path.stat().st_size / max(1, self.n)
