"""gelsim.nuisance.params: the stages' parameters and levels from gelsim/assets/nuisance.toml, and bad files refused."""
import pytest

from gelsim.errors import GelsimError
from gelsim.nuisance import MAX_SEVERITY, NUISANCE_FILE, STAGES, check_severity, load_nuisance


def test_default_file_has_the_three_levels_and_none_is_empty():
    m = load_nuisance()
    assert set(m.levels) == {"none", "camera", "handheld"}
    assert m.level("none") == {}
    assert m.level("camera") == {"exposure": 1.0, "white_balance": 1.0}
    assert list(m.level("handheld")) == [s for s in STAGES if s in m.level("handheld")]   # the stage order
    assert m.level("handheld") == {"fibres": 1.0, "exposure": 1.0, "white_balance": 1.0}
    assert m.level("handheld", severity=2.5) == {"fibres": 2.5, "exposure": 2.5, "white_balance": 2.5}
    assert m.level("handheld", severity=0) == {}
    assert m.stages.exposure.delay_frames == 2 and m.stages.exposure.speed == 0.2
    assert m.stages.fibres.diameter_mm == (0.015, 0.035)


@pytest.mark.parametrize("bad", [-0.1, MAX_SEVERITY + 0.01, float("nan"), float("inf"), "1", True])
def test_severity_out_of_range_is_refused_in_one_line(bad):
    with pytest.raises(GelsimError, match="must be a number from 0") as e:
        check_severity(bad, "--nuisance-severity")
    assert "\n" not in str(e.value)
    with pytest.raises(GelsimError):
        load_nuisance().level("camera", severity=bad)


def test_unknown_level_is_refused():
    with pytest.raises(GelsimError, match="unknown nuisance level 'studio'; choose one of none, camera, handheld"):
        load_nuisance().level("studio")


@pytest.mark.parametrize("edit, match", [
    (("[levels.camera]\n", "[levels.camera]\nambient = 1.0\n"), "unknown stage"),
    (("[levels.none]\n", "[levels.none]\nfibres = 0.5\n"), "switch every stage off"),
    (("exposure = 1.0\nwhite_balance = 1.0\n\n[levels.handheld]", "exposure = 9.0\nwhite_balance = 1.0\n\n[levels.handheld]"),
     "from 0"),
    (("start_ratio = [0.05, 0.6]", "start_ratio = [0.6, 0.05]"), "start_ratio"),
    (("length_mean_mm = 1.5", "length_mean_mm = 1.5\nbogus_mm = 2.0"), "bogus_mm"),
    (("speed = 0.2", "speed = 0.0"), "speed"),
    (("delay_frames = 2", "delay_frames = 0"), "delay_frames"),
    (("start_offset_max = 0.15", "start_offset_max = 0.3"), "start_offset_max"),
    (("[levels.none]\n", "[shades]\nx = 1\n[levels.none]\n"), "unknown table 'shades'"),
])
def test_bad_files_are_refused_naming_the_key(tmp_path, edit, match):
    text = NUISANCE_FILE.read_text()
    assert edit[0] in text
    bad = tmp_path / "n.toml"
    bad.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(GelsimError, match=match) as e:
        load_nuisance(bad)
    assert "\n" not in str(e.value)
