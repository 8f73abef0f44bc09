"""Sharded builds on a real local Ray cluster (started once for the module, 2 CPUs, no mock): stores and index (the
turned descriptors too) identical byte for byte to the in-process build, a build interrupted after some shards
resumes on Ray to the same bytes, a Ray worker killed mid-build (SIGKILL) loses no finished shard and leaves the
same bytes, a full disk leaves no shard taken as complete, an address that does not answer fails in seconds."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from aeroloc.core.errors import AerolocError
from aeroloc.maps.tiling import write_tiles
from aeroloc.matching.features import build_local
from aeroloc.retrieval.database import Database, build_global

ray = pytest.importorskip("ray")

METHOD, RERANK = "xfeat-vlad", "xfeat-lighterglue"
SHARD = 16  # 35 tiles -> shards of 16, 16, 3 (a multiple of the batch size 8)


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def tiles_db(tmp_path_factory, naip_map):
    folder = tmp_path_factory.mktemp("ray") / "tiles"
    write_tiles(naip_map, folder, 1.0, 0.5, progress=False)  # 35 windows, no images
    return folder


def _build(folder, ray_address=None):
    db = Database(folder)
    # with the turned descriptors (--global-turns): their shards read turned map windows on the workers
    build_global(db, METHOD, batch_size=8, progress=False, ray=ray_address, shard_size=SHARD, turns=True)
    build_local(db, RERANK, progress=False, ray=ray_address, shard_size=SHARD)


def _store_files(folder):
    """Every file of the stores and the index (meta.json holds the run's timings: not compared)."""
    return {
        p.relative_to(folder): p.read_bytes()
        for p in sorted((folder / "global").rglob("*")) + sorted((folder / "local").rglob("*"))
        if p.is_file() and p.name != "meta.json"
    }


@pytest.fixture(scope="module")
def in_process(tiles_db, tmp_path_factory):
    folder = tmp_path_factory.mktemp("ref") / "db"
    shutil.copytree(tiles_db, folder)
    _build(folder)
    return folder


def test_ray_build_is_identical_to_the_in_process_build(cluster, tiles_db, in_process, tmp_path):
    folder = tmp_path / "db"
    shutil.copytree(tiles_db, folder)
    _build(folder, "local")  # the module's cluster, 2 actors
    got, want = _store_files(folder), _store_files(in_process)
    assert set(got) == set(want) and len(got) >= 10  # model.pt, 3+3 shards + markers, descriptors, index
    assert any(k.parts[-2:] == ("turns", "descriptors.npy") for k in got)
    assert [k for k in got if got[k] != want[k]] == []
    from aeroloc.retrieval.retriever import Retriever

    a, b = Retriever(Database(folder), METHOD), Retriever(Database(in_process), METHOD)
    image = Database(folder).tile_image("r002c003")
    assert a(image, 5).tile_ids == b(image, 5).tile_ids and a(image, 5).tile_ids[0] == "r002c003"


def test_a_build_interrupted_after_some_shards_resumes_on_ray_to_the_same_bytes(
    cluster, tiles_db, in_process, tmp_path, monkeypatch
):
    from aeroloc.matching.features import LocalTask

    folder = tmp_path / "db"
    shutil.copytree(tiles_db, folder)
    db = Database(folder)
    build_global(db, METHOD, batch_size=8, progress=False, shard_size=SHARD, turns=True)
    real, ran = LocalTask.run, []

    def killed_after_one_shard(self, state, shard, images, ids):
        if ran:
            raise KeyboardInterrupt("worker killed")
        ran.append(shard.index)
        real(self, state, shard, images, ids)

    monkeypatch.setattr(LocalTask, "run", killed_after_one_shard)
    with pytest.raises(KeyboardInterrupt):
        build_local(db, RERANK, progress=False, shard_size=SHARD)
    monkeypatch.undo()
    done = sorted(p.name for p in (folder / "local").rglob("*.done"))
    assert done == ["00000.done"] and not list(folder.rglob("*.part"))
    kept = next((folder / "local").rglob("00000.h5")).stat().st_mtime_ns
    build_local(Database(folder), RERANK, progress=False, ray="local", shard_size=SHARD)
    assert next((folder / "local").rglob("00000.h5")).stat().st_mtime_ns == kept  # finished shard not redone
    got, want = _store_files(folder), _store_files(in_process)
    assert [k for k in want if got.get(k) != want[k]] == []


def _build_actor_pids() -> list[int]:
    """This machine's Ray worker processes running the build's model actors (their title names the class)."""
    pids = []
    for p in Path("/proc").iterdir():
        try:
            if p.name.isdigit() and b"_ShardActor" in (p / "cmdline").read_bytes():
                pids.append(int(p.name))
        except OSError:  # gone meanwhile
            continue
    return pids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds Ray's worker processes in /proc")
def test_a_ray_worker_killed_mid_build_loses_no_finished_shard_and_gives_the_same_bytes(
    cluster, tiles_db, in_process, tmp_path
):
    folder = tmp_path / "db"
    shutil.copytree(tiles_db, folder)
    build_global(Database(folder), METHOD, batch_size=8, progress=False, shard_size=SHARD, turns=True)
    outcome: dict = {}

    def build():
        try:
            build_local(Database(folder), RERANK, progress=False, ray="local", shard_size=SHARD)
        except AerolocError as exc:
            outcome["error"] = str(exc)

    worker = threading.Thread(target=build)
    worker.start()
    deadline = time.monotonic() + 180
    while not list((folder / "local").rglob("*.done")) and time.monotonic() < deadline:
        time.sleep(0.02)
    first = {p.name: p.stat().st_mtime_ns for p in (folder / "local").rglob("*.done")}
    killed = _build_actor_pids()
    for pid in killed:  # every actor of the build, mid-way: no cleanup, no goodbye
        os.kill(pid, signal.SIGKILL)
    worker.join(300)
    # Ray Data restarts the killed actors and gives them the unfinished shards again: the build carries on by
    # itself (were Ray to give up, the one-line "rerun to resume" error of run_on_ray; the test above resumes)
    assert 1 <= len(first) < 3 and killed  # the kill came mid-build: 1 or 2 of the 3 shards finished
    assert not worker.is_alive() and outcome == {}
    for name, mtime in first.items():  # shards finished before the kill were not redone
        assert next((folder / "local").rglob(name)).stat().st_mtime_ns == mtime
    assert not list(folder.rglob("*.part"))
    got, want = _store_files(folder), _store_files(in_process)
    assert [k for k in want if got.get(k) != want[k]] == []


def test_a_full_disk_is_a_clear_error_and_no_shard_is_taken_as_complete(tiles_db, tmp_path, monkeypatch):
    import numpy as np

    folder = tmp_path / "db"
    shutil.copytree(tiles_db, folder)
    real, calls = np.save, []

    def disk_fills(f, arr, *a, **kw):  # the second shard's write hits ENOSPC half-way
        calls.append(1)
        if len(calls) == 2:
            f.write(b"\x93NUMPY partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        real(f, arr, *a, **kw)

    monkeypatch.setattr(np, "save", disk_fills)
    with pytest.raises(AerolocError, match=r"disk full while writing shard 00001 .*rerun the same command"):
        build_global(Database(folder), METHOD, batch_size=8, progress=False, shard_size=SHARD)
    shards = next((folder / "global").iterdir()) / "shards"
    assert sorted(p.name for p in shards.iterdir()) == ["00000.done", "00000.npy"]  # no half shard, no marker
    monkeypatch.undo()
    rep = build_global(Database(folder), METHOD, batch_size=8, progress=False, shard_size=SHARD)
    assert rep.n_tiles == 35 and Database(folder).load_method(METHOD)[1].load().shape == (35, 8192)


def test_an_address_that_does_not_answer_fails_in_seconds():
    import socket

    from aeroloc.retrieval.ray_build import connect

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    with pytest.raises(AerolocError, match=rf"Ray address 127.0.0.1:{port} does not answer"):
        connect(f"127.0.0.1:{port}")
    assert time.perf_counter() - t0 < 10
    with pytest.raises(AerolocError, match="expected HOST:PORT"):
        connect("nonsense")
