"""gelsim.bench.reports: bench.md, bench.json and bench_pareto.png."""
from __future__ import annotations

import json

import pytest

from gelsim import bench
from gelsim.errors import GelsimError


def test_reports(tiny_result, tmp_path):
    paths = bench.write_reports(tiny_result, tmp_path / "r")
    assert json.loads(paths["json"].read_text())["levels"][0]["name"] == "fast"
    md = paths["markdown"].read_text()
    assert "| fast |" in md and "| balanced |" in md and "96x72" in md
    fast = tiny_result["levels"][0]
    assert f"| fabric57-press | {fast['per_scene'][1]['kept_relief']:.2f} /" in md   # the per-scene texture table
    both = {"runs": [tiny_result, tiny_result]}
    paths = bench.write_reports(both, tmp_path / "two")
    assert paths["markdown"].read_text().count("### 96x72") == 2
    png = paths["plot"].read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    (tmp_path / "file").write_text("x")
    with pytest.raises(GelsimError, match="is a file"):
        bench.write_reports(tiny_result, tmp_path / "file")
