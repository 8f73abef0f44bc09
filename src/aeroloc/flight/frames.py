"""Flight readers: a frames CSV, a folder of photos ordered by EXIF time, or a video with telemetry.

Every reader gives the same thing: :class:`FrameRef` per frame (name, time in seconds, what the aircraft knew
as :class:`~aeroloc.core.priors.Priors`, and truth for scoring only) and, lazily, the images. Times must be
present and strictly increasing: a frame out of order would make the motion model jump, so that is a one-line
:class:`AerolocError` naming the row, never a silent reorder. A frame whose image can't be decoded is not an error
of the flight: it is yielded with ``image=None`` and the tracker records it as lost.
"""

from __future__ import annotations

import csv
import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.priors import PRIOR_COLUMNS, Priors, build_priors, parse_value

VIDEO_SUFFIXES = {".mp4", ".mov", ".mkv", ".avi", ".m4v", ".ts"}
FRAME_DIRS = ("frames", "photos", "images", ".")


@dataclass
class FrameRef:
    name: str
    time: float  # seconds (from the first frame's clock: CSV seconds, epoch seconds of ISO/EXIF times, video pts)
    path: Path | None = None  # image file; None for video frames
    priors: Priors = field(default_factory=Priors)
    truth: tuple[float, float] | None = None  # lat, lon: for scoring only, never an input
    origin: str = ""


@dataclass
class Flight:
    """The frames of one flight in time order, and how to read their images."""

    source: Path
    frames: list[FrameRef]
    video: Path | None = None

    def images(self, start: int = 0) -> Iterator[tuple[FrameRef, np.ndarray | None]]:
        """(frame, RGB image or None when it can't be decoded) from frame ``start`` on."""
        if self.video is not None:
            yield from _video_images(self.video, self.frames, start)
            return
        from aeroloc.core.images import read_image

        for ref in self.frames[start:]:
            try:
                img = read_image(ref.path)
            except (AerolocError, OSError, ValueError):
                img = None
            yield ref, img


def parse_time(raw, where: str) -> float:
    """Seconds from a number or an ISO 8601 date-time (naive = UTC); missing or unreadable is an error."""
    s = "" if raw is None else str(raw).strip()
    if not s:
        raise AerolocError(f"{where}: time is missing")
    try:
        v = float(s)
    except ValueError:
        try:
            dt = datetime.fromisoformat(s.replace("Z", "+00:00"))
        except ValueError:
            raise AerolocError(f"{where}: time {s!r} is neither seconds nor ISO 8601") from None
        if dt.tzinfo is None:
            dt = dt.replace(tzinfo=UTC)
        return dt.timestamp()
    if not math.isfinite(v):
        raise AerolocError(f"{where}: time {s!r} is not finite")
    return v


def check_increasing(frames: list[FrameRef]) -> None:
    for a, b in itertools.pairwise(frames):
        if not b.time > a.time:
            raise AerolocError(
                f"{b.origin}: time {b.time:.3f} s is not after the previous frame's ({a.time:.3f} s, {a.name}); "
                "frames must be in capture order with increasing times"
            )


def load_flight(path, telemetry=None, allow_no_telemetry: bool = False) -> Flight:
    """The flight at ``path``: a frames CSV (or a folder holding ``frames.csv``), a folder of photos, or a video."""
    path = Path(path)
    if not path.exists():
        raise AerolocError(f"{path}: flight not found")
    if path.is_dir():
        if (path / "frames.csv").is_file():
            return load_flight(path / "frames.csv", telemetry)
        flight = _photo_folder(path)
    elif path.suffix.lower() in VIDEO_SUFFIXES:
        flight = _video(path, telemetry, allow_no_telemetry)
    else:
        flight = _frames_csv(path)
    if telemetry is not None and flight.video is None:
        apply_telemetry(flight.frames, read_telemetry(telemetry))
    check_increasing(flight.frames)
    return flight


def _frames_csv(path: Path) -> Flight:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        cols = set(reader.fieldnames or [])
        rows = list(reader)
    if not {"name", "time"} <= cols:
        raise AerolocError(f"{path}: missing columns {sorted({'name', 'time'} - cols)} (need name,time)")
    if not rows:
        raise AerolocError(f"{path}: no frames")
    folder = next((path.parent / d for d in FRAME_DIRS if (path.parent / d / rows[0]["name"]).is_file()), path.parent)
    frames = []
    for i, r in enumerate(rows, start=2):
        where = f"{path}:{i}"
        if None in r or None in r.values():
            raise AerolocError(f"{where}: the row does not have the header's {len(cols)} columns")
        values = {c: parse_value(c, r[c], where) for c in PRIOR_COLUMNS if c in cols}
        given = {k: v for k, v in values.items() if v is not None}
        priors = build_priors(given, dict.fromkeys(given, "csv"), where=where) if given else Priors()
        truth = None
        if r.get("lat", "").strip() and r.get("lon", "").strip():
            truth = (float(r["lat"]), float(r["lon"]))
        frames.append(FrameRef(r["name"], parse_time(r["time"], where), folder / r["name"], priors, truth, where))
    return Flight(path, frames)


def exif_time(path: Path) -> float | None:
    """DateTimeOriginal (+ SubSecTimeOriginal) as epoch seconds (the camera's clock, taken as UTC), or None."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)
    except (UnidentifiedImageError, OSError):
        return None
    raw = sub.get(36867) or exif.get(306)
    if not raw:
        return None
    try:
        t = datetime.strptime(str(raw).strip(), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    frac = str(sub.get(37521) or "").strip()

    return t.replace(tzinfo=UTC).timestamp() + (float("0." + frac) if frac.isdigit() else 0.0)


def _photo_folder(folder: Path) -> Flight:
    from aeroloc.core.queries import exif_camera, exif_gps, image_files

    files = image_files(folder, "frames.csv")
    frames = []
    for p in files:
        t = exif_time(p)
        if t is None:
            raise AerolocError(f"{p}: no EXIF capture time (DateTimeOriginal); give a frames CSV name,time instead")
        width, _h, cam, src = exif_camera(p)
        priors = build_priors(cam, src, width_px=width, where=str(p))
        g = exif_gps(p)
        frames.append(FrameRef(p.name, t, p, priors, (g[0], g[1]) if g else None, str(p)))
    times = {}
    for f in frames:
        if f.time in times:
            raise AerolocError(f"{f.origin}: same capture time as {times[f.time]}; the order of the two is unknown")
        times[f.time] = f.name
    frames.sort(key=lambda f: f.time)
    return Flight(folder, frames)


# --- telemetry -------------------------------------------------------------------------------------------------
@dataclass
class Telemetry:
    times: np.ndarray  # seconds, increasing
    columns: dict[str, np.ndarray]  # prior columns (alt_agl_m, heading_deg, ...) and lat/lon (truth), NaN = blank
    source: Path

    def covers(self, t0: float, t1: float) -> bool:
        return len(self.times) > 0 and self.times[0] <= t0 + 1e-6 and self.times[-1] >= t1 - 1e-6

    def at(self, t: float) -> dict[str, float]:
        """The columns interpolated at ``t`` (headings along the short way round)."""
        out = {}
        for k, v in self.columns.items():
            ok = np.isfinite(v)
            if not ok.any():
                continue
            if k == "heading_deg":
                r = np.radians(v[ok])
                s, c = np.interp(t, self.times[ok], np.sin(r)), np.interp(t, self.times[ok], np.cos(r))
                out[k] = float(np.degrees(np.arctan2(s, c)) % 360.0)
            else:
                out[k] = float(np.interp(t, self.times[ok], v[ok]))
        return out


def read_telemetry(path) -> Telemetry:
    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: telemetry file not found")
    if path.suffix.lower() == ".srt":
        return _read_srt(path)
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        cols = [c for c in (reader.fieldnames or []) if c in PRIOR_COLUMNS or c in ("lat", "lon")]
        rows = list(reader)
    if not rows or "time" not in rows[0]:
        raise AerolocError(f"{path}: telemetry needs a header with 'time' and at least one row")
    times = np.array([parse_time(r["time"], f"{path}:{i}") for i, r in enumerate(rows, start=2)])
    if (np.diff(times) <= 0).any():
        i = int(np.argmax(np.diff(times) <= 0)) + 3
        raise AerolocError(f"{path}:{i}: telemetry time is not after the previous row's")
    data = {c: np.array([_num(r.get(c)) for r in rows]) for c in cols}
    return Telemetry(times, data, path)


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


_SRT_TIME = re.compile(r"(\d+):(\d+):(\d+)[,.](\d+)\s*-->")
_SRT_FIELDS = {
    "alt_agl_m": re.compile(r"(?:rel_alt|altitude)\s*[:=]\s*(-?[\d.]+)|\bH\s*(-?[\d.]+)\s*m", re.I),
    "lat": re.compile(r"latitude\s*[:=]\s*(-?[\d.]+)|GPS\s*\(\s*-?[\d.]+\s*,\s*(-?[\d.]+)", re.I),
    "lon": re.compile(r"longitude\s*[:=]\s*(-?[\d.]+)|GPS\s*\(\s*(-?[\d.]+)", re.I),
}


def _read_srt(path: Path) -> Telemetry:
    """A DJI subtitle track: one cue per frame or per second; its start time, height above the take-off point
    (``rel_alt`` / ``H``: taken as height above ground, right over flat ground) and GPS (truth only)."""
    blocks = re.split(r"\n\s*\n", path.read_text(errors="replace"))
    times, rows = [], []
    for b in blocks:
        m = _SRT_TIME.search(b)
        if not m:
            continue
        h, mi, s, ms = (int(x) for x in m.groups())
        times.append(h * 3600 + mi * 60 + s + ms / 10 ** len(m.group(4)))
        row = {}
        for k, rx in _SRT_FIELDS.items():
            f = rx.search(b)
            row[k] = float(next(g for g in f.groups() if g is not None)) if f else math.nan
        rows.append(row)
    if not times:
        raise AerolocError(f"{path}: no subtitle cues (expected DJI .SRT blocks 'hh:mm:ss,ms --> ...')")
    t = np.array(times)
    if (np.diff(t) <= 0).any():
        raise AerolocError(f"{path}: subtitle times are not increasing")
    return Telemetry(t, {k: np.array([r[k] for r in rows]) for k in _SRT_FIELDS}, path)


def apply_telemetry(frames: list[FrameRef], tel: Telemetry) -> None:
    """Each frame's priors from the telemetry at its time (the frame's own columns win); the telemetry must
    cover the frames' times, else the priors would be extrapolated."""
    if frames and not tel.covers(frames[0].time, frames[-1].time):
        raise AerolocError(
            f"{tel.source}: telemetry covers {tel.times[0]:.2f}-{tel.times[-1]:.2f} s but the frames span "
            f"{frames[0].time:.2f}-{frames[-1].time:.2f} s"
        )
    for f in frames:
        vals = tel.at(f.time)
        lat, lon = vals.pop("lat", None), vals.pop("lon", None)
        if f.truth is None and lat is not None and lon is not None:
            f.truth = (lat, lon)
        given = {**{k: v for k, v in vals.items() if k in PRIOR_COLUMNS}, **f.priors.inputs()}
        src = dict.fromkeys(vals, f"telemetry {tel.source.name}") | dict(f.priors.sources)
        if given:
            f.priors = build_priors(given, src, width_px=f.priors.width_px, where=f.origin)


# --- video -----------------------------------------------------------------------------------------------------
def _video(path: Path, telemetry, allow_no_telemetry: bool) -> Flight:
    import av

    if telemetry is None:
        for cand in (path.with_suffix(".SRT"), path.with_suffix(".srt"), path.with_suffix(".csv")):
            if cand.is_file():
                telemetry = cand
                break
    if telemetry is None and not allow_no_telemetry:
        raise AerolocError(
            f"{path}: video without telemetry (give --telemetry CSV or DJI .SRT, or --no-telemetry to track on "
            "the video's own timestamps without priors)"
        )
    try:
        with av.open(str(path)) as c:
            stream = c.streams.video[0]
            base = stream.time_base
            times = [float(p.pts * base) for p in c.demux(stream) if p.pts is not None and p.size > 0]
    except (av.error.FFmpegError, IndexError) as exc:
        raise AerolocError(f"{path}: can't read the video ({exc})") from None
    if not times:
        raise AerolocError(f"{path}: no video frames with timestamps")
    times.sort()  # packets come in decode order; frames are shown in pts order
    t0 = times[0]
    frames = [
        FrameRef(f"{path.stem}_{i:06d}", t - t0, None, Priors(), None, f"{path} frame {i}") for i, t in enumerate(times)
    ]
    if telemetry is not None:
        apply_telemetry(frames, read_telemetry(telemetry))
    return Flight(path, frames, video=path)


def _video_images(path: Path, frames: list[FrameRef], start: int):
    """Decoded frames in presentation order; a frame that fails to decode is yielded as None."""
    import av

    with av.open(str(path)) as c:
        i = 0
        try:
            for frame in c.decode(video=0):
                if i >= len(frames):
                    break
                if i >= start:
                    yield frames[i], frame.to_ndarray(format="rgb24")
                i += 1
        except av.error.FFmpegError:
            pass
        for ref in frames[max(i, start) :]:  # the rest could not be decoded
            yield ref, None
