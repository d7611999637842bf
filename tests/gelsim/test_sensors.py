"""The shipped sensor profiles, `gelsim sensors list`, and their recorded realism."""
from __future__ import annotations

import json

import pytest

from gelsim.cli import main
from gelsim.cli.realism_cmd import realism_report
from gelsim.errors import GelsimError
from gelsim.params import ASSETS_DIR
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
    for name in ("gelsight-r15", "gelsight-mini"):
        v = load_profile(name).unit_variation
        assert v is not None and v.led_intensity_frac > 0 and v.marker_size_frac == 0.0


def test_sensors_list_text_and_json(capsys):
    assert main(["sensors", "list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) >= 4 and lines[0].startswith("profile")
    r15 = [ln for ln in lines if ln.startswith("gelsight-r15")][0]
    assert "640x480" in r15 and f"{realism_records()['gelsight-r15'].skill:.3f}" in r15
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
    # issue #13's targets, held out: at least 0.85 on every pack, 0.90 on the R1.5
    assert recs["gelsight-r15"].skill >= 0.90 and recs["gelsight-mini"].skill >= 0.85
    assert recs["gelsight-mini"].centres == "registered" and recs["gelsight-r15"].centres == "annotated"


def test_realism_record_centres_are_checked(tmp_path):
    text = (ASSETS_DIR / "realism.toml").read_text()
    (tmp_path / "r.toml").write_text(text.replace('centres = "registered"', 'centres = "guessed"'))
    with pytest.raises(GelsimError, match="guessed"):
        realism_records(tmp_path / "r.toml")
    (tmp_path / "r.toml").write_text(text.replace("annotated_skill = 0.736", ""))
    with pytest.raises(GelsimError, match="annotated_skill"):
        realism_records(tmp_path / "r.toml")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["gelsight-r15", "gelsight-mini"])
def test_recorded_realism_is_what_the_profiles_score(name):
    """gelsim/assets/realism.toml holds what `gelsim realism` measures now (data cached only)."""
    rec = realism_records()[name]
    path = taxim_pack_path(rec.datapack)
    if not path.is_file():
        pytest.skip(f"taxim pack {rec.datapack} not cached; run `gelsim realism --datapack {rec.datapack}` once")
    res = realism_report(name, rec.datapack, rec.frames, ball_diameter_mm=rec.ball_diameter_mm, centres=rec.centres)
    assert res["centres"] == rec.centres and res["frames"] == rec.frame_count
    if rec.centres == "registered":
        annotated = evaluate(load_profile(name), load_datapack(path), rec.frames, ball_diameter_mm=rec.ball_diameter_mm)
        assert annotated["skill"] == pytest.approx(rec.annotated_skill, abs=0.001)
    assert res["skill"] == pytest.approx(rec.skill, abs=0.001)
    assert res["contact"]["psnr"] == pytest.approx(rec.contact_psnr_db, abs=0.01)
    assert res["baseline"]["contact"]["psnr"] == pytest.approx(rec.baseline_contact_psnr_db, abs=0.01)
    assert res["small_slope"]["rms_dn"] == pytest.approx(rec.small_slope_rms_dn, abs=0.01)
