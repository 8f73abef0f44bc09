"""One flight tracked into a streamed, resumable CSV (``name,time,lat,lon,status,sigma_m,source,...``).

Rows are flushed as they come (:class:`aeroloc.core.io.ResumableCSV`); a run interrupted and started again with
the same database, flight and settings keeps the finished rows and continues after the last one from its
position, pose and velocity (the odometry chain restarts there). Memory does not grow with the flight: frames
are read one at a time, the tracker keeps its filter state and a few frames' candidates, and with ``keep=False``
the points are not kept either (the CSV holds them: :func:`read_track`); every ``TrackConfig.trim_every`` frames
the C heap's free pages go back to the system.
"""

from __future__ import annotations

from dataclasses import asdict

from aeroloc.core.io import ResumableCSV, config_key, file_identity
from aeroloc.core.provenance import LOCALIZATION_PACKAGES, code_identity
from aeroloc.flight.frames import Flight
from aeroloc.flight.tracker import COLUMNS, TrackConfig, Tracker, TrackPoint, release_native_memory


def signature(db, flight: Flight, options, config: TrackConfig) -> str:
    src = flight.source if flight.source.is_file() else None
    ident = [file_identity(src) if src else "", _frames_identity(flight)]
    # the code too: a finished track of other code is tracked again, not read back as this code's; and torch's
    # thread count: the matchers' float sums differ in their last bits with it, and so can a flight's fixes
    # (NAIP, no metadata, one path: 0.842 of the frames within t on 2 threads, 0.737 on 1)
    code = code_identity((*LOCALIZATION_PACKAGES, "flight"))
    return config_key(
        "track-v1",
        db.tiles_hash(),
        str(flight.source),
        ident,
        len(flight.frames),
        repr(options),
        asdict(config),
        code,
        f"torch threads {_torch_threads()}",
    )


def _frames_identity(flight: Flight) -> list:
    """The frame images themselves, sampled (50 at most): a FRAMES CSV names its images, so images rendered
    again under the same names (a simulator re-run) must not resume the old track. Size and modification time
    of each sampled file (cheap: no image read); the video file's digest."""
    if flight.video is not None:
        return [file_identity(flight.video)]
    out = []
    for f in flight.frames[:: max(1, len(flight.frames) // 50)]:
        st = f.path.stat() if f.path is not None and f.path.is_file() else None
        out.append((f.name, f.time, None if st is None else (st.st_size, st.st_mtime_ns)))
    return out


def _torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def track_flight(
    localizer,
    flight: Flight,
    out,
    config: TrackConfig | None = None,
    on_point=None,
    limit: int | None = None,
    keep: bool = True,
) -> list[TrackPoint] | None:
    """Track ``flight`` into ``out``; ``on_point(point)`` is called for every new point (MAVLink, progress);
    ``limit`` stops after that many frames in all (the rest stays for a resume: tests of interruption). Returns
    every point (a resumed run's earlier ones included), or None with ``keep=False``: a flight of hours then runs
    in flat memory (Python's allocations grew ~0.5 KB a frame with the points kept), and :func:`read_track`
    reads them back from ``out``."""
    config = config or TrackConfig()
    csv = ResumableCSV(out, COLUMNS, signature(localizer.db, flight, localizer.options, config))
    done = csv.finished()
    if done is not None:
        return [TrackPoint.from_row(r) for r in done] if keep else None
    earlier = [TrackPoint.from_row(r) for r in csv.start()]
    tracker = Tracker(localizer, config)
    tracker.restore(earlier)
    n = len(earlier)
    points = earlier if keep else None
    del earlier
    try:
        for ref, image in flight.images(n):
            if limit is not None and n >= limit:
                return points
            p = tracker(ref, image)
            csv.write(p.row())
            n += 1
            if points is not None:
                points.append(p)
            if on_point is not None:
                on_point(p)
            if config.trim_native and config.trim_every and n % config.trim_every == 0:
                release_native_memory()
        csv.finish()
    finally:
        csv.close()
    return points


def read_track(path) -> list[TrackPoint]:
    """The points of a track CSV (:func:`track_flight`'s ``out``), in order."""
    import csv
    from pathlib import Path

    from aeroloc.core.errors import AerolocError

    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: track file not found")
    with open(path, newline="") as f:
        return [TrackPoint.from_row(r) for r in csv.DictReader(f)]
