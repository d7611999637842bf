"""Previews of a generated dataset: the action sheet and the statistics written with them."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gelsim.cli import main
from gelsim.dataset import load_manifest
from gelsim.previews import CONTACT_COLOUR, CROP_COLOUR, action_sheet, pick_across_families
from gelsim.stats import STAM_CPU_CROP, crop_box_px

TINY = ["--fabrics", "3", "--sequences-per-fabric", "2", "--resolution", "96x72", "--fidelity", "fast",
        "--frames", "8-10", "--precontact", "2-3", "--json", "--workers", "1"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("prev") / "ds"
    assert main(["generate", "--out", str(out), *TINY]) == 0
    return out


def test_generate_writes_the_statistics_with_the_previews(tiny):
    prev = tiny / "previews"
    for name in ("dataset_stats.json", "dataset_stats.md", "dataset_stats.png", "dataset_actions.png"):
        assert (prev / name).stat().st_size > 0
    st = json.loads((prev / "dataset_stats.json").read_text())
    m = load_manifest(tiny)
    for a, entry in st["actions"].items():
        assert entry["sequences"] == sum(1 for s in m["sequences"] if s["action"] == a)
    # the table's peak forces are the manifest's, summarised independently here
    press = [s["peak_force_n"] for s in m["sequences"] if s["action"] == "press"]
    assert st["actions"]["press"]["quantities"]["normal_force_n"]["median"] == pytest.approx(np.median(press), rel=1e-5)
    assert not list(prev.glob("*.tmp*")) and not list(prev.glob(".*partial*"))


def test_texture_sheet_shows_each_fabrics_frame_centre_at_its_own_pixels(tiny):
    """Each fabric's peak-force frame at its own pixels, and below it the same minus the flat gel, contrast
    stretched (#50: at 320x240 the frames alone were grey and hazy)."""
    import cv2

    from gelsim.annotate import stretched_difference
    from gelsim.dataset import dataset_flat_frame
    from gelsim.video import read_video

    m = load_manifest(tiny)
    sheet = cv2.imread(str(tiny / "previews" / "texture_sheet.png"))[:, :, ::-1]
    firsts = {}
    for s in m["sequences"]:
        firsts.setdefault(s["fabric_id"], s)
    th, tw = 72, 96   # frames smaller than the 160 x 120 tile are shown whole
    assert sheet.shape == (2 * th, tw * len(firsts), 3)
    flat = dataset_flat_frame(m)
    below_label = slice(20, th)   # the caption's lines end above row 20
    for i, s in enumerate(firsts.values()):
        with np.load(tiny / s["labels"]) as z:
            k = int(np.argmax(z["normal_force_n"]))
        frame = read_video(tiny / s["video"])[k]
        tile = sheet[:th, i * tw:(i + 1) * tw]
        assert np.array_equal(tile[below_label], frame[below_label])
        diff, gain = stretched_difference(frame, flat)
        assert gain > 1 and np.array_equal(sheet[th:, i * tw:(i + 1) * tw][below_label], diff[below_label])


def test_the_flat_gel_is_the_datasets_sensor_before_contact(tiny):
    """The frames before contact differ from the rendered flat gel by the camera's noise and the codec's
    error only: the difference panels show what the contact changed, not another sensor."""
    from gelsim.dataset import dataset_flat_frame
    from gelsim.video import read_video

    m = load_manifest(tiny)
    s = next(s for s in m["sequences"] if s["contact_onset"] >= 2)
    frames = read_video(tiny / s["video"]).astype(float)
    flat = dataset_flat_frame(m, s).astype(float)
    before, contact = np.abs(frames[0] - flat), np.abs(frames[-1] - flat)
    assert before.mean() < 3 and np.percentile(before, 99) < 12, (before.mean(), np.percentile(before, 99))
    other = dataset_flat_frame({**m, "options": {**m["options"], "seed": m["options"]["seed"] + 1}}, s)
    assert np.abs(frames[0] - other).mean() > before.mean() + 1      # another sensor unit's gel is not it
    assert contact.max() > 2 * np.percentile(before, 99)


def test_captions_have_no_ghost_letters():
    """The outline was the text drawn thicker, whose wider glyph advances ran past the white text: "poplin"
    read "poplinn" (#50; 5 px past the white at this size). The outline ends within 3 px of the white glyphs."""
    from gelsim.annotate import caption

    img = caption(np.full((40, 200, 3), 128, np.uint8), ["poplin"], 0.5)
    white = np.flatnonzero((img == 255).all(axis=2).any(axis=0))
    dark = np.flatnonzero((img < 40).all(axis=2).any(axis=0))
    assert white.size and dark.size and dark.max() <= white.max() + 3 and dark.min() >= white.min() - 3


def test_action_strips_show_each_frame_minus_the_flat_gel(tiny):
    import cv2

    strip = cv2.imread(str(tiny / "previews" / "press.png"))
    assert strip.shape == (2 * 180, 6 * 240, 3)       # six 240 px frames, their differences below
    below = strip[180 + 20:, :240].astype(int)
    assert below.std() > 3                              # stretched, not the flat grey of a few DN


def test_centre_crop_takes_the_middle_pixels():
    from gelsim.previews import centre_crop

    f = np.arange(10 * 12 * 3, dtype=np.uint8).reshape(10, 12, 3)
    assert np.array_equal(centre_crop(f, 4, 2), f[4:6, 4:8])
    assert centre_crop(f, 40, 20).shape == f.shape


def test_action_sheet_shows_every_action_with_crop_and_contact(tiny):
    m = load_manifest(tiny)
    sheet = action_sheet(tiny, m, tile_px=96)
    # the 3 tiny fabrics are all plain weaves: one column, rows press, slip, twist
    assert sheet.shape == (3 * 72, 96, 3) and sheet.dtype == np.uint8
    x0, y0, x1, y1 = crop_box_px(96, 72, STAM_CPU_CROP)
    for row in range(3):
        tile = sheet[row * 72:(row + 1) * 72]
        # the crop rectangle's top edge, drawn in its colour (left of the centre: clear of the label text)
        top = tile[int(round(y0 + 0.5 - 0.5)), int(x0) + 2:int(x1) - 2]
        assert (top == CROP_COLOUR).all(axis=1).sum() >= 0.8 * len(top)
        assert (tile == CONTACT_COLOUR).all(axis=2).any()


def _manifest(families):
    fabrics = [{"id": i + 1, "name": f"fab{i + 1}", "family": fam} for i, fam in enumerate(families)]
    seqs = []
    for f in fabrics:
        for k, action in enumerate(("press", "press", "slip", "twist")):
            seqs.append({"id": f"f{f['id']:03d}-s{k:04d}", "fabric_id": f["id"], "action": action,
                         "labels": "x", "video": "y", "peak_force_n": 1.0})
    return {"fabrics": fabrics, "sequences": seqs}


def test_pick_across_families_spreads_and_keeps_one_fabric_per_family():
    fams = ["plain", "plain", "twill", "satin", "knit", "knit", "felt", "mesh"]
    m = _manifest(fams)
    # the first plain fabric has no twist sequence: the family's second one is used for all three
    m["sequences"] = [s for s in m["sequences"] if not (s["fabric_id"] == 1 and s["action"] == "twist")]
    picks = pick_across_families(m, 3)
    assert [f for f, _ in picks] == ["plain", "satin", "mesh"]  # families 0, round(2.5) = 2 and 5 of six
    plain = picks[0][1]
    assert set(plain) == {"press", "slip", "twist"} and {s["fabric_id"] for s in plain.values()} == {2}
    assert plain["press"]["id"] == "f002-s0000"
    assert len(pick_across_families(m, 10)) == 6
    # sequences that never touch are not shown
    for s in m["sequences"]:
        s["peak_force_n"] = 0.0
    assert pick_across_families(m, 3) == []


def test_the_first_look_shows_what_the_contact_changed(tiny):
    """previews/first_look.png and one 960x720 frame per family beside its labelled, stretched difference
    from the flat gel (#42: the demo's previews showed grey frames in which contact and pre-contact looked
    alike)."""
    import cv2

    from gelsim.firstlook import FABRICS, RESOLUTION, first_look_frames, stretched_difference

    prev = tiny / "previews"
    sheet = cv2.imread(str(prev / "first_look.png"))
    w, h = RESOLUTION
    assert sheet.shape == (len(FABRICS) * h // 2, w, 3)
    files = sorted((prev / "first_look").glob("f*.png"))
    assert len(files) == len(FABRICS)
    assert cv2.imread(str(files[0])).shape == (h, 2 * w, 3)
    look = first_look_frames(FABRICS[:1], "vitac")[0]
    assert look["frame"].shape == (h, w, 3)
    diff = look["difference"].astype(int) - 128
    # the contact changed the frame by a few DN; stretched, it spans most of the range
    assert look["gain"] > 2 and np.percentile(np.abs(diff), 99.5) >= 120
    flat = np.full((4, 4, 3), 100, np.uint8)
    img, gain = stretched_difference(flat, flat)
    assert (img == 128).all() and gain == 127.0                     # nothing changed: mid-grey, no division by 0


def test_a_nuisance_level_shows_in_the_first_look(tiny, tmp_path):
    """The handheld dataset's first_look.png was byte-identical to the clean one (#50): with a nuisance level
    the sheet ends with a sequence's first frames as the dataset holds them (the webcam settling) and minus
    the flat gel."""
    import cv2

    from gelsim.firstlook import NUISANCE_FRAMES, RESOLUTION

    out = tmp_path / "handheld"
    assert main(["generate", "--out", str(out), *TINY, "--nuisance", "handheld"]) == 0
    clean = cv2.imread(str(tiny / "previews" / "first_look.png"))
    noisy = cv2.imread(str(out / "previews" / "first_look.png"))
    w = RESOLUTION[0]
    tile_h = round(72 * (w // NUISANCE_FRAMES) / 96)
    assert noisy.shape == (clean.shape[0] + 2 * tile_h, w, 3)
    assert np.array_equal(noisy[:clean.shape[0]], clean)          # the fabrics' rows are the same
    assert not np.array_equal(noisy[clean.shape[0]:clean.shape[0] + tile_h],
                              noisy[clean.shape[0] + tile_h:])         # frames above, differences below


def test_the_first_look_shows_a_sequence_its_nuisance_record_says_was_touched(tiny):
    """A level may touch few recordings: the first look's nuisance rows show the sequence whose per-frame
    record changes most over its first frames."""
    from gelsim.annotate import tile
    from gelsim.dataset import dataset_flat_frame
    from gelsim.firstlook import NUISANCE_FRAMES, RESOLUTION, nuisance_rows, nuisance_shown
    from gelsim.video import read_video

    m = load_manifest(tiny)
    assert nuisance_rows(tiny, m, lambda s: dataset_flat_frame(m, s)) is None          # no level, no rows
    noisy = {**m, "options": {**m["options"], "nuisance": "handheld"}}
    seq = m["sequences"][-1]
    record = tiny / seq["nuisance"]                  # every dataset has one; this one's says nothing was applied
    kept = record.read_bytes()
    try:
        t = seq["num_frames"]
        with record.open("wb") as f:
            np.savez(f, gains=np.linspace(0.3, 1.0, 3 * t).reshape(t, 3).astype(np.float32),
                     fibres_touching=np.zeros(t, np.int32))
        assert nuisance_shown(tiny, seq) == ["gains"] and nuisance_shown(tiny, m["sequences"][0]) == []
        rows = nuisance_rows(tiny, noisy, lambda s: dataset_flat_frame(m, s))
        width = RESOLUTION[0] // NUISANCE_FRAMES
        expected = tile(read_video(tiny / seq["video"])[NUISANCE_FRAMES - 1], width)
        last = rows[:expected.shape[0], (NUISANCE_FRAMES - 1) * width:]
        assert np.array_equal(last[40:], expected[40:])                # below its caption: that sequence's frame
    finally:
        record.write_bytes(kept)


def test_the_first_look_is_rendered_once_per_machine(tmp_path, monkeypatch):
    """Every `gelsim generate` rendered the first look's four 960x720 fabrics anew (4-8 s of a 6-15 s quick
    run): they are kept in the user cache, named by the code that renders them, and read back."""
    from gelsim import firstlook

    monkeypatch.setenv("GELSIM_CACHE", str(tmp_path))
    firstlook._cached_looks.cache_clear()
    fabrics = firstlook.FABRICS[:1]
    first = firstlook._cached_looks(fabrics, "vitac")
    path = firstlook.looks_cache_path(fabrics, "vitac")
    assert path.is_file() and path.is_relative_to(tmp_path)
    firstlook._cached_looks.cache_clear()

    def fail(*args, **kwargs):
        raise AssertionError("rendered again")

    monkeypatch.setattr(firstlook, "first_look_frames", fail)
    again = firstlook._cached_looks(fabrics, "vitac")
    assert [sorted(a) for a in again] == [sorted(a) for a in first]
    for a, b in zip(again, first):
        assert all(np.array_equal(a[k], b[k]) if isinstance(a[k], np.ndarray) else a[k] == b[k] for k in a)
    firstlook._cached_looks.cache_clear()
