"""Shards: the unit of work, storage and resumption of a database build.

A shard is a contiguous run of ``SHARD_TILES`` tiles in ``tiles.csv`` order, so its ids are its positions and
the merged store is the shards one after another. Its pixels are read as a few band windows of the map
(:func:`aeroloc.maps.windows.read_windows`), described in batches that start at the shard start (a multiple of
the batch size, so batches are the same whatever runs the shard), and written to its own files. A shard is
complete only when its marker (``NNNNN.done``) exists: it is written atomically after the shard's data, so an
interrupted or failed write (a full disk) is never taken as complete and is redone on the next run.

The same :func:`run_shard` runs in-process (:func:`run_in_process`) and on Ray workers
(:mod:`aeroloc.retrieval.ray_build`), which is what makes the two builds identical byte for byte.
"""

from __future__ import annotations

import contextlib
import errno
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_path, write_json_atomic

SHARD_TILES = 256  # a multiple of every batch size used (16, 32), ~14 MB of map pixels for 256 px tiles
TORCH_THREADS = 1  # XFeat keypoints differ in the last bits between 1 and 2 torch threads: every shard uses 1


@dataclass(frozen=True)
class Shard:
    """Tiles ``start`` .. ``stop`` - 1 of the database."""

    index: int
    start: int
    stop: int

    @property
    def name(self) -> str:
        return f"{self.index:05d}"

    def __len__(self) -> int:
        return self.stop - self.start


def plan(n_tiles: int, size: int = SHARD_TILES) -> list[Shard]:
    """The shards of ``n_tiles`` tiles, in order."""
    if size < 1:
        raise AerolocError(f"shard size must be >= 1, got {size}")
    return [Shard(i, s, min(s + size, n_tiles)) for i, s in enumerate(range(0, n_tiles, size))]


def shard_of(position: int, size: int = SHARD_TILES) -> int:
    return position // size


class ShardTask(Protocol):
    """One kind of per-shard output (global descriptors, local features). ``open`` loads the model once per
    process; ``run`` describes the shard's images (tile ``ids``) and writes the shard and its marker; ``folder``
    holds the shard files. A task with a ``read(source, shard)`` method reads its own images (e.g. the tiles'
    turned views); otherwise they are the shard's tiles."""

    folder: Path

    def open(self) -> Any: ...

    def run(self, state: Any, shard: Shard, images: list[np.ndarray], ids: list[str]) -> None: ...


@dataclass(frozen=True)
class ShardJob:
    """Everything a worker needs to build shards: the database folder and the task (picklable, small)."""

    db_folder: str
    task: Any  # a ShardTask
    shard_size: int = SHARD_TILES
    meta: dict = field(default_factory=dict)

    def shards(self, n_tiles: int) -> list[Shard]:
        return plan(n_tiles, self.shard_size)

    def todo(self, n_tiles: int) -> list[Shard]:
        return [s for s in self.shards(n_tiles) if not is_complete(self.task.folder, s)]


def marker(folder: Path, shard: Shard) -> Path:
    return Path(folder) / "shards" / f"{shard.name}.done"


def is_complete(folder: Path, shard: Shard) -> bool:
    """The shard's marker exists and names this shard's tiles."""
    p = marker(folder, shard)
    try:
        m = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return m.get("start") == shard.start and m.get("stop") == shard.stop


def write_shard_file(path: Path, write: Callable[[Path], None]) -> None:
    """``write(tmp)`` then rename onto ``path``; a full disk becomes a one-line error (nothing left half)."""
    try:
        with atomic_path(path) as tmp:
            write(tmp)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise AerolocError(
                f"{path.parent}: disk full while writing shard {path.stem} ({exc.strerror}); free space and rerun "
                "the same command to resume from the finished shards"
            ) from None
        raise


def mark_complete(folder: Path, shard: Shard, extra: dict | None = None) -> None:
    """Written after the shard's data: from now on the shard counts as built."""
    p = marker(folder, shard)
    try:
        write_json_atomic(p, {"start": shard.start, "stop": shard.stop, **(extra or {})})
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise AerolocError(f"{p.parent}: disk full while marking shard {shard.name} ({exc.strerror})") from None
        raise


class ShardRunner:
    """A worker's view of a job: the database's pixels (tiles + map) and the task's loaded state, opened once."""

    def __init__(self, job: ShardJob):
        import torch

        from aeroloc.maps.tilesource import TileSource

        torch.set_num_threads(TORCH_THREADS)
        self.job = job
        self.source = TileSource(job.db_folder)
        self.state = job.task.open()

    def __call__(self, shard: Shard) -> int:
        return run_shard(self.job, self.source, self.state, shard)


def run_shard(job: ShardJob, source, state, shard: Shard) -> int:
    """Read the shard's windows, run the task on them, write its files and marker; returns its tile count."""
    if is_complete(job.task.folder, shard):
        return 0
    read = getattr(job.task, "read", None)  # a task that reads its own pixels (e.g. turned views)
    images = read(source, shard) if read is not None else list(source.images(shard.start, shard.stop))
    job.task.run(state, shard, images, [t.id for t in source.tiles[shard.start : shard.stop]])
    return len(shard)


@contextlib.contextmanager
def torch_threads(n: int = TORCH_THREADS):
    """torch at ``n`` intra-op threads inside the block, the caller's count restored after it."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def run_in_process(job: ShardJob, shards: list[Shard], progress: Callable[[int], None] | None = None) -> None:
    """The shards one after another in this process (same code as the Ray workers, same torch threads)."""
    with torch_threads():
        runner = ShardRunner(job)
        for shard in shards:
            n = runner(shard)
            if progress:
                progress(n)


def iter_rows(path: Path, chunk: int = 4096) -> Iterator[np.ndarray]:
    """The rows of a ``.npy`` file in chunks, each mapped and released in turn (RAM flat in the file's size)."""
    n = np.load(path, mmap_mode="r").shape[0]
    for s in range(0, n, chunk):
        mm = np.load(path, mmap_mode="r")
        block = np.array(mm[s : s + chunk])
        del mm
        yield block


__all__ = [
    "SHARD_TILES",
    "Shard",
    "ShardJob",
    "ShardRunner",
    "ShardTask",
    "is_complete",
    "iter_rows",
    "mark_complete",
    "plan",
    "run_in_process",
    "run_shard",
    "shard_of",
    "write_shard_file",
]
