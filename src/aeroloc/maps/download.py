"""Download a map from a tile server or the Google Static Maps API into a map folder, surviving what real
servers do: rate limits (429 + Retry-After), 5xx bursts, timeouts, dropped connections, HTML error pages
served with 200, truncated bodies, and crashes of the downloader itself.

How: a thread pool shares a token-bucket rate limit; each tile is retried with exponential backoff and jitter
(``Retry-After`` honoured); a response is kept only if Pillow decodes all of it at the expected size; files
are written atomically (temp + rename), so a re-run skips every tile already on disk and valid and fetches
the rest. Keys stay in memory: messages, logs and manifest hold ``***`` or nothing.

Output layouts (read by aeroloc.maps.sources):
- XYZ: ``MAPDIR/{z}/{x}/{y}.{png|jpg|webp}`` (the bytes exactly as served) + ``manifest.json`` (layout "xyz");
- Google Static: ``tile_RRRR_CCCC.png`` (logo strip cropped) + ``map_metadata.txt`` (the seed's layout:
  header, then ``filename top_left_lat top_left_lon bottom_right_lat bottom_right_lon`` row-major, north row
  first, outer pixel edges) + ``manifest.json`` (layout "metadata").
"""

from __future__ import annotations

import datetime as _dt
import email.utils
import io
import json
import logging
import random
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import requests

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_write_bytes
from aeroloc.maps.providers import GoogleStaticProvider, XYZProvider, check_bbox, google_grid, redact, xyz_grid

log = logging.getLogger("aeroloc.maps.download")

IMAGE_EXTS = {"PNG": ".png", "JPEG": ".jpg", "WEBP": ".webp"}
USER_AGENT = "aeroloc-map-downloader/0.1 (+https://github.com/aeroloc)"
MAX_BODY_BYTES = 32 * 1024 * 1024


# --- failures (messages are shown to users: built from status codes and exception types, key-free) ---------
class TileError(Exception):
    """One attempt at one tile failed. ``retry``: worth another attempt; ``fatal``: stop the whole run."""

    def __init__(self, reason: str, retry: bool = True, fatal: bool = False, retry_after: float | None = None):
        super().__init__(reason)
        self.reason, self.retry, self.fatal, self.retry_after = reason, retry, fatal, retry_after


class InvalidImage(TileError):
    pass


# --- pacing ------------------------------------------------------------------------------------------------
class TokenBucket:
    """At most ``rate`` requests per second on average, bursts up to ``burst``; shared by all threads."""

    def __init__(self, rate: float, burst: float | None = None, clock=time.monotonic, sleep=time.sleep):
        if not rate > 0:
            raise AerolocError(f"rate {rate}: must be > 0 requests per second")
        self.rate, self.capacity = float(rate), float(burst if burst else max(1.0, rate))
        self.tokens, self.clock, self.sleep = self.capacity, clock, sleep
        self.stamp = clock()
        self.lock = threading.Lock()

    def acquire(self) -> None:
        while True:
            with self.lock:
                now = self.clock()
                self.tokens = min(self.capacity, self.tokens + (now - self.stamp) * self.rate)
                self.stamp = now
                if self.tokens >= 1 - 1e-9:  # tolerance: float refills can land a hair under 1
                    self.tokens = max(0.0, self.tokens - 1)
                    return
                wait_s = (1 - self.tokens) / self.rate
            self.sleep(wait_s)


@dataclass
class RetryPolicy:
    """How hard to try one tile. ``sleep`` and ``rng`` are injectable so tests run without waiting."""

    attempts: int = 6
    backoff_s: float = 0.5  # first retry waits ~this long, doubling each time
    max_backoff_s: float = 60.0
    max_retry_after_s: float = 300.0  # honour Retry-After up to this
    connect_timeout_s: float = 10.0
    read_timeout_s: float = 30.0
    total_timeout_s: float = 120.0  # a body trickling in slower than this is abandoned
    sleep: Callable[[float], None] = time.sleep
    rng: random.Random = field(default_factory=random.Random)

    def delay(self, attempt: int, retry_after: float | None = None) -> float:
        """Wait before attempt ``attempt + 1`` (attempt counts from 1): 'equal jitter' exponential backoff,
        never shorter than the server's Retry-After."""
        d = min(self.max_backoff_s, self.backoff_s * 2 ** (attempt - 1))
        d = d / 2 + self.rng.uniform(0, d / 2)
        if retry_after is not None:
            d = max(d, min(retry_after, self.max_retry_after_s))
        return d


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """Seconds from a Retry-After header (delta-seconds or HTTP date); None when absent or unreadable."""
    if not value:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when is None:
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.UTC)
    now = time.time() if now is None else now
    return max(0.0, when.timestamp() - now)


# --- validation ----------------------------------------------------------------------------------------------
def decode_image(data: bytes, expect_size: tuple[int, int] | None = None):
    """The decoded Pillow image and its file extension, or InvalidImage (HTML page, truncated, wrong size)."""
    from PIL import Image, UnidentifiedImageError

    if not data:
        raise InvalidImage("empty body")
    head = data[:64].lstrip().lower()
    if head.startswith((b"<", b"{")):
        raise InvalidImage("not an image (HTML/JSON/XML body)")
    try:
        im = Image.open(io.BytesIO(data))
        im.load()  # decodes every byte: a truncated body fails here
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise InvalidImage(f"undecodable image ({type(exc).__name__})") from None
    ext = IMAGE_EXTS.get(im.format or "")
    if ext is None:
        raise InvalidImage(f"unsupported image format {im.format}", retry=False)
    if expect_size and im.size != tuple(expect_size):
        raise InvalidImage(
            f"image is {im.size[0]}x{im.size[1]} px, expected {expect_size[0]}x{expect_size[1]}", retry=False
        )
    return im, ext


def valid_file(path: Path, expect_size: tuple[int, int] | None) -> bool:
    try:
        decode_image(path.read_bytes(), expect_size)
        return True
    except (InvalidImage, OSError):
        return False


# --- one request -----------------------------------------------------------------------------------------------
_session = threading.local()


def _thread_session() -> requests.Session:
    """One Session (connection pool, keep-alive) per worker thread: requests.Session is not thread-safe."""
    s = getattr(_session, "s", None)
    if s is None:
        s = _session.s = requests.Session()
        s.headers["User-Agent"] = USER_AGENT
    return s


def fetch_once(url: str, policy: RetryPolicy, secret: str | None = None) -> bytes:
    """One GET; the body if it is a 200, else TileError describing what happened (without the URL)."""
    try:
        start = time.monotonic()
        with _thread_session().get(url, timeout=(policy.connect_timeout_s, policy.read_timeout_s), stream=True) as resp:
            status = resp.status_code
            if status != 200:
                raise _status_error(status, resp)
            chunks, size = [], 0
            for chunk in resp.iter_content(64 * 1024):
                chunks.append(chunk)
                size += len(chunk)
                if size > MAX_BODY_BYTES:
                    raise TileError(f"body larger than {MAX_BODY_BYTES >> 20} MB", retry=False)
                if time.monotonic() - start > policy.total_timeout_s:
                    raise TileError(f"body slower than {policy.total_timeout_s:g} s")
            return b"".join(chunks)
    except TileError:
        raise
    except requests.Timeout:
        raise TileError("timeout") from None
    except requests.RequestException as exc:
        # the text of a requests exception can hold the URL (and so the key): keep only the gist
        gist = redact(str(exc), secret)
        gist = "truncated body" if "IncompleteRead" in gist else type(exc).__name__
        raise TileError(f"connection error: {gist}") from None


def _status_error(status: int, resp) -> TileError:
    reason = f"HTTP {status}"
    if status in (401, 403):
        return TileError(f"{reason}: access refused (check the key or the provider's terms)", retry=False, fatal=True)
    if status == 429 or status == 503:
        return TileError(reason, retry_after=parse_retry_after(resp.headers.get("Retry-After")))
    if status in (408, 425) or status >= 500:
        return TileError(reason)
    return TileError(reason, retry=False)  # 204, 404, 410 …: this tile does not exist here


# --- jobs --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TileJob:
    """One image to fetch. ``label`` is what users see; ``url`` may hold the key and is never shown."""

    label: str
    url: str = field(repr=False)
    stem: Path  # destination without extension
    expect_size: tuple[int, int] | None  # of the response
    final_size: tuple[int, int] | None  # of the saved file
    exts: tuple[str, ...] = (".png", ".jpg", ".webp")
    transform: Callable | None = field(default=None, repr=False)  # (bytes, PIL image) -> (bytes, ext) to save

    def existing(self) -> Path | None:
        for ext in self.exts:
            p = self.stem.with_suffix(ext)
            if p.is_file():
                return p
        return None


@dataclass
class DownloadReport:
    expected: int = 0
    downloaded: int = 0
    skipped: int = 0  # already on disk and valid
    failed: dict = field(default_factory=dict)  # label -> last reason
    retries: int = 0
    bytes: int = 0
    seconds: float = 0.0
    aborted: str | None = None
    fatal: bool = False  # stopped by a refusal (401/403) or an unwritable folder
    retry_reasons: Counter = field(default_factory=Counter)

    @property
    def tiles_per_s(self) -> float:
        return self.downloaded / self.seconds if self.seconds > 0 else 0.0

    @property
    def complete(self) -> bool:
        return not self.failed and self.aborted is None and self.downloaded + self.skipped == self.expected

    def summary(self, limit: int = 10) -> str:
        lines = [
            f"{self.downloaded} tiles downloaded, {self.skipped} already present, {len(self.failed)} missing "
            f"of {self.expected} in {self.seconds:.1f} s ({self.tiles_per_s:.1f} tiles/s, "
            f"{self.bytes / 1e6:.1f} MB, {self.retries} retries"
            + (f": {', '.join(f'{k} x{v}' for k, v in self.retry_reasons.most_common(5))}" if self.retries else "")
            + ")"
        ]
        if self.aborted:
            lines.append(f"stopped early: {self.aborted}")
        if self.failed:
            by_reason = Counter(self.failed.values())
            lines.append("missing tiles by reason: " + "; ".join(f"{r} ({n})" for r, n in by_reason.most_common()))
            shown = list(self.failed)[:limit]
            lines.append(
                "missing: "
                + ", ".join(shown)
                + (" …" if len(self.failed) > limit else "")
                + " — run the same command again to fetch only these"
            )
        return "\n".join(lines)


def _save(job: TileJob, data: bytes, im, ext: str) -> Path:
    if job.transform is not None:
        data, ext = job.transform(data, im)
    dest = job.stem.with_suffix(ext)
    for other in job.exts:  # a stale file of another format would make two tiles for one cell
        if other != ext and job.stem.with_suffix(other).exists():
            job.stem.with_suffix(other).unlink()
    atomic_write_bytes(dest, data)
    return dest


def fetch_tile(
    job: TileJob,
    policy: RetryPolicy,
    bucket: TokenBucket,
    secret: str | None,
    stop: threading.Event,
    report: DownloadReport,
    lock: threading.Lock,
) -> Path | None:
    """Try one tile up to ``policy.attempts`` times; the saved path, or TileError with the last reason."""
    last: TileError | None = None
    for attempt in range(1, policy.attempts + 1):
        if stop.is_set():
            raise TileError("not attempted (run stopped)", retry=False)
        bucket.acquire()
        try:
            data = fetch_once(job.url, policy, secret)
            im, ext = decode_image(data, job.expect_size)
            try:
                path = _save(job, data, im, ext)
            except OSError as exc:
                raise TileError(
                    f"cannot write {job.stem.parent}: {exc.strerror or exc}", retry=False, fatal=True
                ) from None
            with lock:
                report.bytes += len(data)
            return path
        except TileError as exc:
            exc.reason = redact(exc.reason, secret)
            last = exc
            if exc.fatal or not exc.retry or attempt == policy.attempts:
                break
            delay = policy.delay(attempt, exc.retry_after)
            with lock:
                report.retries += 1
                report.retry_reasons[exc.reason.split(":")[0]] += 1
            log.debug(
                "tile %s: %s (attempt %d/%d), retrying in %.2f s",
                job.label,
                exc.reason,
                attempt,
                policy.attempts,
                delay,
            )
            policy.sleep(delay)
    assert last is not None
    if last.retry and last.reason != "not attempted (run stopped)":
        last.reason = f"{last.reason} (after {policy.attempts} attempts)"
    raise last


def remove_partial_files(folder: Path) -> int:
    """Delete temp files a killed run left behind (``.name.part`` from atomic writes)."""
    n = 0
    if folder.is_dir():
        for p in folder.rglob(".*.part"):
            try:
                p.unlink()
                n += 1
            except OSError:
                pass
    return n


def download_tiles(
    jobs: list[TileJob],
    *,
    workers: int = 4,
    rate: float = 8.0,
    policy: RetryPolicy | None = None,
    secret: str | None = None,
    progress: bool = True,
    max_consecutive_failures: int = 50,
    bucket: TokenBucket | None = None,
) -> DownloadReport:
    """Fetch every job not already on disk and valid. Ctrl-C (or any crash) stops cleanly: finished tiles stay,
    no partial file is left, and the next run resumes. A refusal (401/403) or an unwritable folder stops the
    run: ``report.fatal`` is set and the tiles not fetched are listed as failed."""
    if workers < 1:
        raise AerolocError(f"workers {workers}: must be >= 1")
    policy = policy or RetryPolicy()
    bucket = bucket or TokenBucket(rate)
    report, lock, stop = DownloadReport(expected=len(jobs)), threading.Lock(), threading.Event()
    start = time.monotonic()

    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="aeroloc-dl")
    try:
        pending = _not_on_disk(pool, jobs, progress)  # 1. resume: keep tiles already saved and decodable
        report.skipped = len(jobs) - len(pending)
        streak = _FailureStreak(max_consecutive_failures, stop, lock)

        def fetch(job: TileJob) -> Path | None:
            try:
                path = fetch_tile(job, policy, bucket, secret, stop, report, lock)
            except TileError as exc:
                streak.failed(exc)
                raise
            streak.succeeded()
            return path

        futures = {pool.submit(fetch, job): job for job in pending}
        _collect(futures, report, stop, progress)  # 2. fetch the rest
        if streak.message and not report.aborted:
            report.aborted = streak.message
    except BaseException:
        stop.set()  # workers finish the tile in hand (atomic write) and take no new one
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    report.seconds = time.monotonic() - start
    return report


def _not_on_disk(pool: ThreadPoolExecutor, jobs: list[TileJob], progress: bool) -> list[TileJob]:
    """The jobs whose tile is not saved yet, or saved but not decodable at its size (checked in parallel)."""
    from tqdm import tqdm

    def present(job):
        p = job.existing()
        return p is not None and valid_file(p, job.final_size)

    checks = tqdm(
        pool.map(present, jobs),
        total=len(jobs),
        unit="tile",
        desc="verify on disk",
        leave=False,
        disable=not progress,
    )
    return [job for job, ok in zip(jobs, checks) if not ok]


def _collect(futures: dict, report: DownloadReport, stop: threading.Event, progress: bool):
    """Count the fetches as they finish; a fatal error sets ``stop`` (the jobs not started yet then fail as 'not
    attempted'; so does a streak of failures, :class:`_FailureStreak`, in the workers)."""
    from tqdm import tqdm

    bar = tqdm(
        total=len(futures), unit="tile", desc="download", disable=not progress, dynamic_ncols=True, smoothing=0.1
    )
    try:
        for fut in as_completed(futures):  # O(n) overall, unlike repeated wait() on the whole set
            job = futures[fut]
            try:
                fut.result()
                report.downloaded += 1
            except TileError as exc:
                _record_failure(job, exc, report, stop)
            bar.update(1)
            bar.set_postfix(missing=len(report.failed), retries=report.retries, refresh=False)
    finally:
        bar.close()


def _record_failure(job: TileJob, exc: TileError, report: DownloadReport, stop: threading.Event) -> None:
    """Note one failed tile; a fatal one stops the run."""
    report.failed[job.label] = exc.reason
    if exc.fatal:
        if not report.fatal:
            report.aborted, report.fatal = f"tile {job.label}: {exc.reason}", True
        stop.set()


class _FailureStreak:
    """Failures in a row, counted by the workers as each tile ends: ``max_consecutive`` of them stop the run
    before a worker takes its next tile. Counted where the results are collected instead, a worker failing
    fast (a refused connection) ran ahead of the collecting thread on a loaded machine: one worker tried 9
    tiles of an unreachable server before the stop after 5."""

    def __init__(self, max_consecutive: int, stop: threading.Event, lock: threading.Lock):
        self.max, self.stop, self.lock = max_consecutive, stop, lock
        self.count = 0
        self.message = ""

    def succeeded(self) -> None:
        with self.lock:
            self.count = 0

    def failed(self, exc: TileError) -> None:
        if exc.fatal or exc.reason == "not attempted (run stopped)":
            return
        with self.lock:
            self.count += 1
            if self.count >= self.max and not self.stop.is_set():
                self.message = f"{self.count} tiles in a row failed (last: {exc.reason}); is the server reachable?"
                self.stop.set()


# --- whole maps ----------------------------------------------------------------------------------------------
def _now() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()


def _write_json(path: Path, info: dict) -> None:
    atomic_write_bytes(path, (json.dumps(info, indent=1) + "\n").encode())


def _check_same_map(out: Path, plan: dict) -> None:
    """A folder holds one download: resuming with another area/zoom/provider would mix two maps."""
    manifest = out / "manifest.json"
    if not manifest.is_file():
        if out.is_dir() and ((out / "map_metadata.txt").exists() or any(p.name.isdigit() for p in out.iterdir())):
            raise AerolocError(f"{out}: holds tiles but no manifest.json; choose an empty --out folder")
        return
    try:
        old = json.loads(manifest.read_text())
    except json.JSONDecodeError:
        raise AerolocError(f"{manifest}: not valid JSON; delete it or choose another --out folder") from None
    diff = [k for k in ("layout", "provider", "zoom", "x_range", "y_range", "grid") if old.get(k) != plan.get(k)]
    if diff:
        raise AerolocError(
            f"{out}: already holds another download ("
            + ", ".join(f"{k} {old.get(k)!r} vs {plan.get(k)!r}" for k in diff)
            + "); choose another --out folder"
        )


@dataclass
class _Plan:
    manifest: dict  # layout-specific manifest keys
    jobs: list
    missing_id: Callable  # TileJob -> what tiles_missing lists
    prepare: Callable = lambda: None  # write layout files (map_metadata.txt) once the folder is checked


def download_map(
    out,
    bbox,
    zoom: int,
    provider,
    *,
    key: str | None = None,
    workers: int = 4,
    rate: float = 8.0,
    policy: RetryPolicy | None = None,
    progress: bool = True,
    max_tiles: int = 50_000,
    bucket: TokenBucket | None = None,
    max_consecutive_failures: int = 50,
) -> tuple[DownloadReport, dict]:
    """Download the tiles of ``provider`` covering ``bbox`` (south, west, north, east) at ``zoom`` into ``out``.

    Returns the report and the manifest written to ``out/manifest.json``; ``tiles_missing`` lists what is
    still to fetch and running again fetches only that. ``key`` goes into requests only. A refusal (401/403)
    or an unwritable folder raises AerolocError after the manifest is saved.
    """
    out = Path(out)
    bbox = check_bbox(bbox)
    plan = _plan(out, bbox, zoom, provider, key, max_tiles)
    _check_same_map(out, plan.manifest)
    out.mkdir(parents=True, exist_ok=True)
    remove_partial_files(out)
    manifest = {
        **plan.manifest,
        "bbox_requested": list(bbox),
        "created": _now(),
        "tiles_expected": len(plan.jobs),
        "tiles_missing": None,
        "complete": False,
    }
    _write_json(out / "manifest.json", manifest)  # first, so a killed run still describes its folder
    plan.prepare()
    report = None
    try:
        report = download_tiles(
            plan.jobs,
            workers=workers,
            rate=rate,
            policy=policy,
            secret=key,
            progress=progress,
            bucket=bucket,
            max_consecutive_failures=max_consecutive_failures,
        )
    finally:
        _finish_manifest(out, plan, manifest, report)
    if report.fatal:
        raise AerolocError(f"{provider.name}: {redact(report.aborted, key)}; finished tiles are kept in {out}")
    return report, manifest


def _plan(out: Path, bbox, zoom: int, provider, key, max_tiles: int) -> _Plan:
    if isinstance(provider, GoogleStaticProvider):
        return _google_plan(out, bbox, zoom, provider, key, max_tiles)
    if isinstance(provider, XYZProvider):
        return _xyz_plan(out, bbox, zoom, provider, key, max_tiles)
    raise AerolocError(f"unknown provider object {type(provider).__name__}")


def _finish_manifest(out: Path, plan: _Plan, manifest: dict, report: DownloadReport | None) -> None:
    """Record what is still missing (all of what is not on disk and decodable when the run crashed, ``report``
    None) and, for templates without a format, the one the server sent; rewrite ``manifest.json``."""
    if report is not None:
        missing = [j for j in plan.jobs if j.label in report.failed]
    else:  # crashed: trust only what is on disk and decodes
        missing = [j for j in plan.jobs if not ((p := j.existing()) and valid_file(p, j.final_size))]
    manifest.update(tiles_missing=[plan.missing_id(j) for j in missing], complete=not missing, updated=_now())
    if "ext_note" in manifest:  # the template named no format: say which one the server sent
        exts = Counter(p.suffix for j in plan.jobs if (p := j.existing()))
        if exts:
            manifest["ext"] = exts.most_common(1)[0][0].lstrip(".")
    _write_json(out / "manifest.json", manifest)


def _check_count(n: int, zoom: int, max_tiles: int) -> None:
    if n > max_tiles:
        raise AerolocError(
            f"{n} images at zoom {zoom} exceed --max-tiles {max_tiles}; lower the zoom, shrink "
            "the area or raise --max-tiles"
        )


def _xyz_plan(out: Path, bbox, zoom: int, provider: XYZProvider, key, max_tiles: int) -> _Plan:
    if provider.max_zoom is not None and zoom > provider.max_zoom:
        raise AerolocError(f"zoom {zoom}: provider {provider.name} serves zooms up to {provider.max_zoom}")
    grid = xyz_grid(bbox, zoom)
    _check_count(grid.n_tiles, zoom, max_tiles)
    size = (provider.tile_size, provider.tile_size)
    suffix = provider.suffix
    exts = (suffix,) if suffix else tuple(IMAGE_EXTS.values())
    transform = _keep_as(suffix) if suffix else None
    jobs = [
        TileJob(
            f"{zoom}/{x}/{y}",
            provider.url(zoom, x, y, key),
            out / str(zoom) / str(x) / str(y),
            size,
            size,
            exts=exts,
            transform=transform,
        )
        for x, y in grid.tiles()
    ]
    manifest = {
        "layout": "xyz",
        "zoom": zoom,
        "x_range": [grid.x0, grid.x1],
        "y_range": [grid.y0, grid.y1],
        "tile_size": provider.tile_size,
        "ext": (suffix or ".png").lstrip("."),
        "provider": provider.name,
        "attribution": provider.attribution,
        "bounds": list(grid.bounds()),
    }
    if not suffix:
        manifest["ext_note"] = "the template names no format: each file keeps the format served (png/jpg/webp)"
    return _Plan(manifest, jobs, lambda j: [int(v) for v in j.label.split("/")[1:]])


def _keep_as(suffix: str):
    """Save under the template's extension: the served bytes as they are, re-encoded only if the server sent
    another format than the template promises."""
    fmt = {".png": "PNG", ".jpg": "JPEG", ".webp": "WEBP"}[suffix]

    def transform(data: bytes, im):
        if im.format == fmt:
            return data, suffix
        buf = io.BytesIO()
        im.convert("RGB" if fmt == "JPEG" else "RGBA").save(buf, format=fmt)
        return buf.getvalue(), suffix

    return transform


def _google_plan(out: Path, bbox, zoom: int, provider: GoogleStaticProvider, key, max_tiles: int) -> _Plan:
    grid = google_grid(bbox, zoom, provider.size, provider.scale, provider.crop_px)
    _check_count(grid.n_tiles, zoom, max_tiles)
    size, final = (grid.image_px, grid.image_px), (grid.tile_w, grid.tile_h)

    def crop_logo(data: bytes, im):
        buf = io.BytesIO()
        im.convert("RGB").crop((0, 0, grid.tile_w, grid.tile_h)).save(buf, format="PNG", compress_level=3)
        return buf.getvalue(), ".png"

    cells = list(grid.cells())
    jobs = [
        TileJob(
            c.filename,
            provider.url(c, zoom, key),
            out / Path(c.filename).stem,
            size,
            final,
            exts=(".png",),
            transform=crop_logo,
        )
        for c in cells
    ]
    manifest = {
        "layout": "metadata",
        "zoom": zoom,
        "tile_size": [grid.tile_w, grid.tile_h],
        "ext": "png",
        "grid": {
            "rows": grid.n_rows,
            "cols": grid.n_cols,
            "left_px": grid.left,
            "top_px": grid.top,
            "render_zoom": grid.render_zoom,
            "scale": grid.scale,
            "logo_crop_px": grid.crop_px,
        },
        "provider": provider.name,
        "attribution": provider.attribution,
        "bounds": list(grid.bounds()),
        "metadata": "map_metadata.txt",
    }

    def write_metadata():
        lines = ["filename top_left_lat top_left_lon bottom_right_lat bottom_right_lon"]
        lines += [
            f"{c.filename} {c.corners[0]:.12f} {c.corners[1]:.12f} {c.corners[2]:.12f} {c.corners[3]:.12f}"
            for c in cells
        ]
        atomic_write_bytes(out / "map_metadata.txt", ("\n".join(lines) + "\n").encode())

    return _Plan(manifest, jobs, lambda j: j.label, write_metadata)


__all__ = [
    "DownloadReport",
    "InvalidImage",
    "RetryPolicy",
    "TileError",
    "TileJob",
    "TokenBucket",
    "decode_image",
    "download_map",
    "download_tiles",
    "fetch_once",
    "fetch_tile",
    "parse_retry_after",
    "remove_partial_files",
]
