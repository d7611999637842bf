"""The shipped sensor profiles, `gelsim sensors list`, and their recorded realism."""
from __future__ import annotations

import json

import pytest

from gelsim.cli import main
from gelsim.realism import evaluate, load_datapack, realism_records, taxim_pack_path
from gelsim.sensor import list_profiles, load_profile


def test_shipped_profiles_load_and_calibrated_ones_have_a_table():
    names = list_profiles()
    assert {"gelsight-r15", "gelsight-mini", "digit", "vitac"} <= set(names)
    for n in names:
        p = load_profile(n)
        assert p.name == n and p.description
    assert load_profile("gelsight-mini").shading.model == "lut"
    digit = load_profile("digit")
    assert digit.shape == (320, 240) and digit.markers.enabled is False
    assert digit.unit_variation is not None


def test_sensors_list_text_and_json(capsys):
    assert main(["sensors", "list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) >= 4 and lines[0].startswith("profile")
    r15 = [ln for ln in lines if ln.startswith("gelsight-r15")][0]
    assert "640x480" in r15 and "0.947" in r15
    assert main(["sensors", "list", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = {r["name"]: r for r in doc["sensors"]}
    assert len(rows) >= 3
    v = rows["vitac"]
    assert v["field_mm"] == pytest.approx([960 * 0.0197, 720 * 0.0197], abs=1e-3)
    assert v["markers"]["size_mm"] == 0.4 and v["realism"] is None
    assert v["unit_variation"]["led_intensity_frac"] > 0
    assert rows["gelsight-mini"]["realism"]["skill"] == realism_records()["gelsight-mini"].skill
    assert main(["sensors"]) == 2


def test_realism_records_cover_the_calibrated_profiles():
    recs = realism_records()
    assert set(recs) == {"gelsight-r15", "gelsight-mini"}
    for name, r in recs.items():
        p = load_profile(name)
        assert r.mm_per_px == pytest.approx(p.image.mm_per_px)
        assert r.contact_psnr_db > r.baseline_contact_psnr_db and r.skill > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["gelsight-r15", "gelsight-mini"])
def test_recorded_realism_is_what_the_profiles_score(name):
    """assets/realism.toml holds what `gelsim realism` measures now (data cached only)."""
    rec = realism_records()[name]
    path = taxim_pack_path(rec.datapack)
    if not path.is_file():
        pytest.skip(f"taxim pack {rec.datapack} not cached; run `gelsim realism --datapack {rec.datapack}` once")
    res = evaluate(load_profile(name), load_datapack(path), rec.frames, ball_diameter_mm=rec.ball_diameter_mm)
    assert res["frames"] == rec.frame_count
    assert res["skill"] == pytest.approx(rec.skill, abs=0.001)
    assert res["contact"]["psnr"] == pytest.approx(rec.contact_psnr_db, abs=0.01)
    assert res["baseline"]["contact"]["psnr"] == pytest.approx(rec.baseline_contact_psnr_db, abs=0.01)
    assert res["small_slope"]["rms_dn"] == pytest.approx(rec.small_slope_rms_dn, abs=0.01)
