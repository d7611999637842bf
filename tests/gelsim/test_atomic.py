"""gelsim.atomic: the one atomic writer and the one PNG writer."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from gelsim import atomic
from gelsim.errors import GelsimError


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if atomic.PARTIAL in p.name)


def test_whole_documents_replace_atomically_and_create_folders(tmp_path):
    target = tmp_path / "a" / "b" / "doc.json"
    atomic.atomic_write_json(target, {"x": [1, 2]})
    assert json.loads(target.read_text()) == {"x": [1, 2]} and target.read_text().endswith("\n")
    atomic.atomic_write_text(target, "second")
    assert target.read_text() == "second"
    atomic.atomic_write_npz(tmp_path / "z.npz", a=np.arange(3))
    with np.load(tmp_path / "z.npz") as z:
        np.testing.assert_array_equal(z["a"], np.arange(3))
    assert _leftovers(target.parent) == [] and _leftovers(tmp_path) == []


def test_json_keeps_numpy_values_and_paths(tmp_path):
    doc = {"n": np.int64(3), "x": np.float32(0.5), "a": np.arange(3), "p": tmp_path / "f.png"}
    atomic.atomic_write_json(tmp_path / "d.json", doc)
    assert json.loads((tmp_path / "d.json").read_text()) == {"n": 3, "x": 0.5, "a": [0, 1, 2],
                                                             "p": str(tmp_path / "f.png")}
    with pytest.raises(TypeError, match="not JSON serialisable: object"):
        atomic.json_default(object())


def test_a_failing_writer_leaves_the_old_file_and_no_partial(tmp_path):
    target = tmp_path / "keep.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic.atomic_open(target) as f:
            f.write(b"half of the new")
            raise RuntimeError("killed mid-write")
    assert target.read_bytes() == b"old"
    assert _leftovers(tmp_path) == []


def test_partial_name_is_what_generate_sweeps(tmp_path):
    p = atomic.partial_path(tmp_path / "x.mp4", suffix=".mp4")
    assert p.parent == tmp_path and p.name.startswith(".x.mp4.partial-") and p.suffix == ".mp4"
    assert list(tmp_path.glob(".*.partial-*")) == [] and p.match(".*.partial-*")


def test_unwritable_place_is_one_line_gelsim_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(GelsimError, match="cannot write there") as e:
        atomic.atomic_write_bytes(blocker / "x.bin", b"data")
    assert "\n" not in str(e.value) and "x.bin" in str(e.value)


def test_png_round_trip_keeps_rgb_order_and_grey(tmp_path):
    rgb = np.zeros((5, 7, 3), np.uint8)
    rgb[..., 0] = 200          # red
    rgb[2, 3] = (10, 20, 30)
    atomic.write_png(tmp_path / "c.png", rgb)
    back = cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    np.testing.assert_array_equal(back, rgb)
    atomic.write_png(tmp_path / "bgr.png", rgb, rgb=False)    # already BGR: stored as given
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "bgr.png"), cv2.IMREAD_UNCHANGED), rgb)
    grey = np.arange(35, dtype=np.uint8).reshape(5, 7)
    atomic.write_png(tmp_path / "g.png", grey)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "g.png"), cv2.IMREAD_UNCHANGED), grey)
    assert atomic.png_bytes(rgb) == (tmp_path / "c.png").read_bytes()


@pytest.mark.parametrize("img", [np.zeros((4, 4, 3), np.float64), np.zeros((4, 4, 5), np.uint8),
                                 np.zeros((0, 4, 3), np.uint8)])
def test_png_refuses_what_is_not_an_8bit_image(tmp_path, img):
    with pytest.raises(GelsimError, match="uint8"):
        atomic.write_png(tmp_path / "bad.png", img)
    assert not (tmp_path / "bad.png").exists()


def test_write_figure_writes_a_png_and_closes_the_figure(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2, 1))
    ax.plot([0, 1], [1, 0])
    path = atomic.write_figure(tmp_path / "fig.png", fig, dpi=50)
    img = cv2.imread(str(path))
    assert img is not None and img.shape[:2] == (50, 100)
    assert not plt.fignum_exists(fig.number)


def test_check_out_file(tmp_path):
    assert atomic.check_out_file(tmp_path / "x.PNG") == tmp_path / "x.PNG"
    with pytest.raises(GelsimError, match="must be a .png file"):
        atomic.check_out_file(tmp_path / "x.jpg")
    with pytest.raises(GelsimError, match="does not exist"):
        atomic.check_out_file(tmp_path / "missing" / "x.png")
    assert atomic.check_out_file(tmp_path / "t.toml", ".toml").name == "t.toml"
