"""The pipeline commands as a user runs them (subprocess): bad input is one line on stderr and exit code 2, no
traceback, and nothing is built before the input is known to be good."""

from __future__ import annotations

import subprocess
import sys

import pytest


def aeroloc(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "aeroloc.cli", *map(str, args)], capture_output=True, text=True, timeout=120, cwd=cwd
    )


def one_line_error(p: subprocess.CompletedProcess, command: str) -> str:
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert "Traceback" not in p.stderr + p.stdout
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith(f"aeroloc {command}: error: "), lines[0]
    return lines[0]


def test_build_missing_map(tmp_path):
    missing = tmp_path / "no_such_map.tif"
    line = one_line_error(aeroloc("build", missing, "--out", tmp_path / "db"), "build")
    assert "no_such_map.tif" in line and "not found" in line
    assert not (tmp_path / "db").exists()


def test_build_zoom_zero(naip_map, tmp_path):
    line = one_line_error(aeroloc("build", naip_map, "--zoom", 0, "--out", tmp_path / "db"), "build")
    assert "zoom" in line
    assert not (tmp_path / "db").exists()


@pytest.mark.parametrize("option, kind", [("--method", "retrieval method"), ("--local", "re-ranker")])
def test_build_unknown_method_or_reranker_fails_before_any_work(naip_map, tmp_path, option, kind):
    line = one_line_error(aeroloc("build", naip_map, option, "no-such-thing", "--out", tmp_path / "db"), "build")
    assert f"unknown {kind} 'no-such-thing'" in line
    assert "xfeat-vlad" in line if option == "--method" else "xfeat-lighterglue" in line  # the choices
    assert not (tmp_path / "db").exists()  # no tiles rendered, no descriptors computed for nothing


def test_localize_unknown_reranker(naip_tiles_db, naip_dev, tmp_path):
    out = tmp_path / "results.csv"
    p = aeroloc("localize", naip_tiles_db, naip_dev, "--rerank", "no-such-reranker", "--out", out)
    line = one_line_error(p, "localize")
    assert "unknown re-ranker 'no-such-reranker'" in line and "xfeat-lighterglue" in line
    assert not out.exists()


def test_localize_on_a_folder_that_is_not_a_database(naip_dev, tmp_path):
    line = one_line_error(aeroloc("localize", tmp_path, naip_dev, "--out", tmp_path / "r.csv"), "localize")
    assert "tiles.csv" in line


def test_methods_lists_the_offline_defaults():
    p = aeroloc("methods")
    assert p.returncode == 0, p.stderr
    names = {line.split()[0].rstrip(":") for line in p.stdout.splitlines() if line.startswith("  ")}
    assert {"xfeat-vlad", "effnet-vlad", "xfeat-lighterglue", "aliked-lightglue"} <= names
    assert "retrieval methods" in p.stdout and "re-rankers" in p.stdout
