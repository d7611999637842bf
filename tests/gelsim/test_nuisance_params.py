"""gelsim.nuisance.params: the stages' parameters and levels from gelsim/assets/nuisance.toml, and bad files refused."""
import pytest

from gelsim.errors import GelsimError
from gelsim.nuisance import MAX_SEVERITY, NUISANCE_FILE, STAGES, check_severity, load_nuisance


def test_default_file_has_the_four_levels_and_none_is_empty():
    m = load_nuisance()
    assert set(m.levels) == {"none", "camera", "handheld", "webcam-restart"}
    assert m.level("none") == {}
    assert m.level("camera") == {"startup": 1.0}
    assert list(m.level("handheld")) == [s for s in STAGES if s in m.level("handheld")]   # the stage order
    assert m.level("handheld") == {"fibres": 1.0, "startup": 1.0}
    assert m.level("handheld", severity=2.5) == {"fibres": 2.5, "startup": 2.5}
    assert m.level("handheld", severity=0) == {}
    assert m.stages.startup.exposure_delay_frames == 2 and m.stages.startup.exposure_settle_frames == (6, 10)
    assert m.stages.fibres.diameter_mm == (0.015, 0.035)


def test_a_levels_parameters_replace_the_files_for_that_level_only():
    m = load_nuisance()
    assert m.stages_for("webcam-restart").startup.restart_share == 1.0
    assert m.stages_for("camera") == m.stages and m.stages_for("handheld") == m.stages
    assert m.stages.startup.restart_share < 0.1
    assert m.level("webcam-restart") == m.level("camera")
    with pytest.raises(GelsimError, match="unknown nuisance level"):
        m.stages_for("studio")


@pytest.mark.parametrize("bad", [-0.1, MAX_SEVERITY + 0.01, float("nan"), float("inf"), "1", True])
def test_severity_out_of_range_is_refused_in_one_line(bad):
    with pytest.raises(GelsimError, match="must be a number from 0") as e:
        check_severity(bad, "--nuisance-severity")
    assert "\n" not in str(e.value)
    with pytest.raises(GelsimError):
        load_nuisance().level("camera", severity=bad)


def test_unknown_level_is_refused():
    with pytest.raises(GelsimError, match="unknown nuisance level 'studio'; choose one of none, camera, handheld, webcam-restart"):
        load_nuisance().level("studio")


@pytest.mark.parametrize("edit, match", [
    (("[levels.camera]\n", "[levels.camera]\nambient = 1.0\n"), "unknown stage"),
    (("[levels.none]\n", "[levels.none]\nfibres = 0.5\n"), "switch every stage off"),
    (("[levels.camera]\n# the webcam's start-up, where ViTac's recordings can have caught it (the first touch of a cloth)\nstartup = 1.0",
      "[levels.camera]\nstartup = 9.0"), "from 0"),
    (("exposure_start = [0.05, 0.6]", "exposure_start = [0.6, 0.05]"), "exposure_start"),
    (("length_mean_mm = 1.5", "length_mean_mm = 1.5\nbogus_mm = 2.0"), "bogus_mm"),
    (("restart_share = 0.033", "restart_share = 1.5"), "restart_share"),
    (("exposure_settle_frames = [6, 10]", "exposure_settle_frames = [2, 10]"), "exposure_settle_frames"),
    (("exposure_settle_frames = [6, 10]", "exposure_settle_frames = [6.5, 10]"), "expected an integer"),
    (("white_balance_start_max = 0.15", "white_balance_start_max = 1.0"), "white_balance_start_max"),
    (("[levels.webcam-restart.params.startup]\nrestart_share = 1.0", "[levels.webcam-restart.params.startup]\nrestart_share = 2.0"),
     "webcam-restart.params.startup.restart_share"),
    (("[levels.webcam-restart.params.startup]\nrestart_share = 1.0", "[levels.webcam-restart.params.startup]\nshare = 1.0"),
     "unknown parameter"),
    (("[levels.webcam-restart.params.startup]", "[levels.webcam-restart.params.flicker]"), "unknown stage"),
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
