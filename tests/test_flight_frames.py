"""Flight readers on real data: frames CSV times and bad input, Toledo photos in EXIF time order, telemetry
coverage, DJI .SRT subtitles, and a real video encoded with PyAV from Toledo photos."""

from __future__ import annotations

import csv
import itertools
import shutil

import numpy as np
import pytest

from aeroloc.core.errors import AerolocError
from aeroloc.flight.frames import exif_time, load_flight, read_telemetry


def _photos(data_dir, n=4):
    return sorted((data_dir / "toledo" / "photos").glob("*.JPG"))[:n]


def _frames_csv(tmp_path, data_dir, times, extra=None):
    folder = tmp_path / "frames"
    folder.mkdir(exist_ok=True)
    photos = _photos(data_dir, len(times))
    for p in photos:
        shutil.copy(p, folder / p.name)
    path = tmp_path / "frames.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["name", "time", *(extra or {})])
        for p, t in zip(photos, times, strict=True):
            w.writerow([p.name, t, *((extra or {}).values())])
    return path


def test_photo_folder_is_ordered_by_exif_time(data_dir):
    flight = load_flight(data_dir / "toledo" / "photos")
    times = [f.time for f in flight.frames]
    assert len(flight.frames) == 57
    assert all(b > a for a, b in itertools.pairwise(times))
    assert times == sorted(exif_time(f.path) for f in flight.frames)
    # EXIF GPS is kept as truth for scoring, never as a prior
    assert all(f.truth is not None for f in flight.frames)
    assert all(f.priors.gsd_m is None for f in flight.frames)


def test_frames_csv_reads_seconds_and_iso_times(tmp_path, data_dir):
    path = _frames_csv(tmp_path, data_dir, ["2015-10-16T12:59:14", "2015-10-16T12:59:27.5Z", "2015-10-16T13:00:00"])
    flight = load_flight(path)
    assert [round(b.time - a.time, 3) for a, b in zip(flight.frames, flight.frames[1:], strict=False)] == [13.5, 32.5]
    path = _frames_csv(tmp_path, data_dir, [0, 0.5, 1.0], {"alt_agl_m": "100", "hfov_deg": "60"})
    f = load_flight(path).frames[0]
    img_w = 1200
    assert f.priors.with_image_width(img_w).gsd_m == pytest.approx(2 * 100 * np.tan(np.radians(30)) / img_w)


@pytest.mark.parametrize(
    ("times", "message"),
    [
        ([0, 2, 1], "is not after the previous frame"),
        ([0, 1, 1], "is not after"),
        ([0, "", 2], "time is missing"),
        ([0, "soon", 2], "neither seconds nor ISO"),
    ],
)
def test_bad_times_are_one_line_errors(tmp_path, data_dir, times, message):
    path = _frames_csv(tmp_path, data_dir, times)
    with pytest.raises(AerolocError, match=message) as e:
        load_flight(path)
    assert "\n" not in str(e.value) and "frames.csv:" in str(e.value)


def test_an_undecodable_frame_is_yielded_as_none(tmp_path, data_dir):
    path = _frames_csv(tmp_path, data_dir, [0, 1, 2])
    broken = tmp_path / "frames" / _photos(data_dir, 3)[1].name
    broken.write_bytes(b"not a jpeg")
    got = [(ref.name, img is None) for ref, img in load_flight(path).images()]
    assert [g[1] for g in got] == [False, True, False]


def test_telemetry_must_cover_the_frames(tmp_path, data_dir):
    path = _frames_csv(tmp_path, data_dir, [0, 1, 2])
    tel = tmp_path / "telemetry.csv"
    tel.write_text("time,alt_agl_m,hfov_deg\n0,100,60\n1.5,120,60\n")
    with pytest.raises(AerolocError, match=r"telemetry covers 0\.00-1\.50 s but the frames span 0\.00-2\.00 s"):
        load_flight(path, tel)
    tel.write_text("time,alt_agl_m,hfov_deg\n0,100,60\n2,120,60\n")
    frames = load_flight(path, tel).frames
    gsd = [f.priors.with_image_width(1200).gsd_m for f in frames]
    assert gsd[1] == pytest.approx(2 * 110 * np.tan(np.radians(30)) / 1200)  # interpolated at t = 1 s


def test_dji_srt_subtitles(tmp_path):
    srt = tmp_path / "DJI_0001.SRT"
    srt.write_text(
        '1\n00:00:00,000 --> 00:00:00,033\n<font size="28">FrameCnt: 1 [latitude: 41.549407] '
        "[longitude: -83.698919] [rel_alt: 52.300 abs_alt: 241.1]</font>\n\n"
        '2\n00:00:01,000 --> 00:00:01,033\n<font size="28">FrameCnt: 31 [latitude: 41.549500] '
        "[longitude: -83.698900] [rel_alt: 54.300 abs_alt: 243.1]</font>\n"
    )
    tel = read_telemetry(srt)
    assert tel.times.tolist() == [0.0, 1.0]
    assert tel.at(0.5)["alt_agl_m"] == pytest.approx(53.3)
    assert tel.at(0.0)["lat"] == pytest.approx(41.549407)


def _video(tmp_path, data_dir, n=6):
    import av

    from aeroloc.core.images import read_image

    path = tmp_path / "flight.mp4"
    with av.open(str(path), "w") as out:
        s = out.add_stream("mpeg4", rate=2)
        s.width, s.height, s.pix_fmt = 320, 240, "yuv420p"
        for p in _photos(data_dir, n):
            img = np.ascontiguousarray(read_image(p)[::4, ::4][:240, :320])
            for pkt in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(pkt)
        for pkt in s.encode():
            out.mux(pkt)
    return path


def test_video_needs_telemetry_that_covers_it(tmp_path, data_dir):
    path = _video(tmp_path, data_dir)
    with pytest.raises(AerolocError, match="video without telemetry"):
        load_flight(path)
    flight = load_flight(path, allow_no_telemetry=True)
    assert len(flight.frames) == 6
    assert [round(f.time, 3) for f in flight.frames] == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    images = [img for _, img in flight.images()]
    assert all(img is not None and img.shape == (240, 320, 3) for img in images)
    tel = tmp_path / "short.csv"
    tel.write_text("time,alt_agl_m,hfov_deg\n0,50,60\n1.0,50,60\n")
    with pytest.raises(AerolocError, match="telemetry covers"):
        load_flight(path, tel)
