"""Run a build's shards on a Ray cluster with Ray Data: the shard list is a dataset, a pool of model actors
(one CPU each, the model loaded once per actor) reads each shard's windows from the map, describes them in
batches and writes the shard's files to the shared database folder.

Each actor runs the very :class:`~aeroloc.retrieval.shards.ShardRunner` the in-process build runs (same batches,
same torch threads), so the stores are identical byte for byte. Ray is optional (``aeroloc[ray]``); an address
that does not answer fails within seconds with one line, not after Ray's own minute of retries.
"""

from __future__ import annotations

import socket
from collections.abc import Callable

from aeroloc.core.errors import AerolocError
from aeroloc.retrieval.shards import Shard, ShardJob, ShardRunner

CONNECT_TIMEOUT_S = 5.0
LOCAL = "local"  # --ray without an address: start a local cluster on this machine


def _import_ray():
    try:
        import ray
    except ImportError:
        raise AerolocError("--ray needs the ray package: pip install 'aeroloc[ray]'") from None
    return ray


def _probe(address: str) -> None:
    """A TCP connect to the cluster's head (host:port, optionally ray://) within ``CONNECT_TIMEOUT_S``."""
    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise AerolocError(f"Ray address {address!r}: expected HOST:PORT (e.g. 10.0.0.5:6379), 'auto' or 'local'")
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise AerolocError(
            f"Ray address {address} does not answer ({exc.strerror or exc}); is 'ray start' running?"
        ) from None


def connect(address: str | None = LOCAL, num_cpus: int | None = None):
    """The ``ray`` module, connected: to ``address`` (HOST:PORT, ray://HOST:PORT, auto), or a new local cluster
    for ``local``/None; an already initialised Ray (a test's ``ray.init``) is used as it is."""
    ray = _import_ray()
    if address not in (None, "", LOCAL, "auto"):
        _probe(address)
    if ray.is_initialized():
        return ray
    kwargs = {"include_dashboard": False, "log_to_driver": False, "ignore_reinit_error": True}
    try:
        if address in (None, "", LOCAL):
            ray.init(num_cpus=num_cpus, **kwargs)
        else:
            ray.init(address=address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise AerolocError(f"Ray address {address}: cannot connect ({str(exc).splitlines()[0][:200]})") from None
    return ray


class _ShardActor:
    """A Ray Data actor: one ShardRunner (model loaded once), one shard per batch row."""

    def __init__(self, job: ShardJob):
        self.runner = ShardRunner(job)

    def __call__(self, batch: dict) -> dict:
        import numpy as np

        done = []
        for index, start, stop in zip(batch["index"], batch["start"], batch["stop"]):
            done.append(self.runner(Shard(int(index), int(start), int(stop))))
        return {"index": np.asarray(batch["index"]), "n": np.asarray(done)}


def _root_error(exc: BaseException) -> BaseException:
    """The AerolocError a worker raised, through Ray's wrappers (RayTaskError.cause, __cause__ chains)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, AerolocError):
            return exc
        exc = getattr(exc, "cause", None) or exc.__cause__
    return None


def run_on_ray(
    job: ShardJob,
    shards: list[Shard],
    address: str | None = LOCAL,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Build ``shards`` of ``job`` on the cluster at ``address`` with ``workers`` model actors (default: the
    cluster's CPUs). Shards finished before (their markers) are never sent."""
    if not shards:
        return
    ray = connect(address)
    n_actors = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    n_actors = min(n_actors, len(shards))
    items = [{"index": s.index, "start": s.start, "stop": s.stop} for s in shards]
    # one block per shard, made in the driver: no upstream tasks compete with the actors for the CPUs
    ds = ray.data.from_items(items, override_num_blocks=len(items))
    ds = ds.map_batches(_ShardActor, fn_constructor_args=(job,), batch_size=1, concurrency=n_actors, num_cpus=1)
    try:
        for row in ds.iter_rows():
            if progress:
                progress(int(row["n"]))
    except Exception as exc:
        root = _root_error(exc)
        if root is not None:
            raise AerolocError(str(root)) from None
        raise AerolocError(
            f"Ray build failed ({type(exc).__name__}: {str(exc).splitlines()[0][:200]}); "
            "rerun to resume from the finished shards"
        ) from None


__all__ = ["CONNECT_TIMEOUT_S", "connect", "run_on_ray"]
