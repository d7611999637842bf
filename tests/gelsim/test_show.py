"""`gelsim show`: pictures of one sequence (gelsim.show)."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from gelsim.cli import main
from gelsim.dataset import load_manifest
from gelsim.show import load_look, marker_frames, pick_frames
from gelsim.video import count_frames

TINY = ["--fabrics", "2", "--sequences-per-fabric", "2", "--resolution", "96x72", "--fidelity", "fast",
        "--frames", "8-10", "--precontact", "2-3", "--no-previews", "--json", "--workers", "1"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("show") / "ds"
    assert main(["generate", "--out", str(out), *TINY]) == 0
    return out


def _png(path):
    img = cv2.imread(str(path))
    assert img is not None, path
    return img


def test_show_writes_the_frames_the_markers_the_labels_and_a_video(tiny, tmp_path, capsys):
    m = load_manifest(tiny)
    seq = m["sequences"][1]
    out = tmp_path / "look"
    assert main(["show", str(tiny), seq["id"], "--out", str(out), "--frames", "4", "--video", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["sequence"] == seq["id"] and res["frames"] == seq["num_frames"]
    assert res["nuisance_record"]              # every dataset holds one; with no level it records nothing applied
    assert sorted(p.name for p in out.iterdir()) == ["frames.png", "labels.png", "markers.png", "video.mp4"]
    # frames.png: 4 frames of 96 x 72 px, each above its difference from the flat gel
    strip = _png(out / "frames.png")
    assert strip.shape == (2 * 72, 4 * 96, 3)
    assert strip[72 + 30:, :].std() > 3                     # the differences are stretched, not flat grey
    # markers.png: panels enlarged to at least 480 px, one per picked frame, with the arrows' colour
    sheet = _png(out / "markers.png")[:, :, ::-1]
    look = load_look(tiny, seq["id"])
    panels = len(marker_frames(look))
    assert sheet.shape == (72 * 5, panels * 96 * 5, 3)
    assert ((sheet == (255, 230, 40)).all(axis=2)).sum() > 20
    assert _png(out / "labels.png").shape[0] > 400
    assert count_frames(out / "video.mp4") == seq["num_frames"]


def test_show_defaults_to_a_sequence_in_contact_and_a_folder_in_the_dataset(tiny, capsys):
    assert main(["show", str(tiny)]) == 0
    files = capsys.readouterr().out.split()
    look = load_look(tiny)
    assert look.onset is not None
    assert files == [str(tiny / "previews" / look.sequence["id"] / f) for f in ("frames.png", "markers.png",
                                                                                 "labels.png")]


def test_a_nuisance_record_gets_a_panel_per_value_that_changes(tiny, tmp_path):
    """Where the dataset holds a per-frame nuisance record of the sequence (``nuisance/fNNN/<id>.npz``, the
    manifest entry's ``nuisance``), each of its per-frame values that changes over the sequence gets a panel
    under the labels; constant "nothing applied" rows and values not per frame get none."""
    from gelsim.annotate import nuisance_record, varying_nuisance
    from gelsim.show import labels_figure

    seq = load_manifest(tiny)["sequences"][0]
    plain = labels_figure(load_look(tiny, seq["id"]), tmp_path / "plain.png")
    path = tiny / seq["nuisance"]          # every dataset's record: overwritten here and put back after
    kept = path.read_bytes()
    assert not varying_nuisance(nuisance_record(tiny, seq), seq["num_frames"])     # no level: nothing varies
    try:
        t = seq["num_frames"]
        with open(path, "wb") as f:
            np.savez(f, gains=np.linspace(0.2, 1.0, 3 * t).reshape(t, 3).astype(np.float32),
                     stream_age_frames=np.arange(t, dtype=np.int32), fibres_touching=np.zeros(t, np.int32),
                     note=np.array("not per frame"))
        rec = nuisance_record(tiny, seq)
        assert set(rec) == {"gains", "stream_age_frames", "fibres_touching", "note"}
        assert set(varying_nuisance(rec, t)) == {"gains", "stream_age_frames"}
        with_record = labels_figure(load_look(tiny, seq["id"]), tmp_path / "with.png")
        assert _png(with_record).shape[0] > _png(plain).shape[0] + 200     # two more panels
    finally:
        path.write_bytes(kept)


def test_pick_frames_keeps_the_ends():
    assert pick_frames(10, 4) == [0, 3, 6, 9]
    assert pick_frames(3, 8) == [0, 1, 2]
    assert pick_frames(5, 1) == [0]
