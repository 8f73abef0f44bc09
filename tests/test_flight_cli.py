"""The two flight commands: simulate-flight writes a flight folder; track refuses bad input with one line."""

from __future__ import annotations

import csv

from aeroloc.cli import main


def test_simulate_flight_then_bad_times_are_one_line_errors(tmp_path, naip_map, naip_dev, capsys):
    out = tmp_path / "fl"
    code = main(
        [
            "simulate-flight",
            str(naip_map),
            str(naip_dev),
            "--out",
            str(out),
            "--frames",
            "12",
            "--gap",
            "4",
            "--size",
            "160x120",
        ]
    )
    assert code == 0
    capsys.readouterr()
    with open(out / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 10 and all((out / "frames" / r["name"]).is_file() for r in rows)
    with open(out / "truth.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == 10
    # the same frames with two rows swapped: refused before any work, naming the row
    rows[3], rows[4] = rows[4], rows[3]
    bad = out / "swapped.csv"
    with open(bad, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["name", "time"])
        w.writeheader()
        w.writerows(rows)
    code = main(["track", str(tmp_path / "no-db"), str(bad), "--out", str(tmp_path / "t.csv")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "swapped.csv:6" in err and "is not after the previous frame" in err
    code = main(
        [
            "track",
            str(tmp_path / "no-db"),
            str(out / "frames.csv"),
            "--out",
            str(tmp_path / "t.csv"),
            "--telemetry",
            str(tmp_path / "none.csv"),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and "telemetry file not found" in err and len(err.splitlines()) == 1
