import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.video import VideoWriter, count_frames, read_video, video_path, write_video


def _frames(n=5, h=48, w=64):
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([60 + 2 * xx, 80 + yy, 120 + xx + yy], -1).clip(0, 255).astype(np.uint8)
    # smooth content plus a moving square, like a tactile frame
    out = []
    for i in range(n):
        f = base.copy()
        f[10:20, 5 + 3 * i:15 + 3 * i] = 20
        out.append(f)
    return out


@pytest.mark.parametrize("fmt", ["h264", "ffv1", "png"])
def test_roundtrip_frame_count_and_content(tmp_path, fmt):
    frames = _frames()
    p = video_path(tmp_path / "seq", fmt)
    write_video(p, frames, fmt=fmt)
    v = read_video(p)
    assert v.shape == (5, 48, 64, 3) and v.dtype == np.uint8
    err = np.abs(v.astype(int) - np.stack(frames).astype(int)).mean()
    if fmt == "h264":
        assert err < 8  # lossy, but close at CRF 18
    else:
        assert err == 0  # lossless
    assert count_frames(p) == 5
    # no temporary files left behind
    assert [q.name for q in tmp_path.iterdir()] == [p.name]


@pytest.mark.parametrize("h, w", [(48, 128), (48, 70)])   # 70: chroma rows of 35 px are padded, no reuse
def test_reused_yuv_frame_writes_the_same_file(tmp_path, h, w):
    """The writer refills one yuv420p frame; a new frame per write (PyAV's from_ndarray) gives the same bytes."""
    frames = _frames(n=6, h=h, w=w)
    reused = write_video(tmp_path / "reused.mp4", frames)
    fresh = VideoWriter(tmp_path / "fresh.mp4")
    fresh._planes = None            # the from_ndarray path
    with fresh:
        for f in frames:
            fresh.write(f)
    writer = VideoWriter(tmp_path / "probe.mp4")
    writer.write(frames[0])
    assert (writer._frame is not None) == (w == 128)   # the reuse path was taken where it can be
    writer.abort()
    assert reused.read_bytes() == (tmp_path / "fresh.mp4").read_bytes()
    assert read_video(reused).shape == (6, h, w, 3)


def test_odd_size_h264(tmp_path):
    frames = _frames(h=33, w=47)
    p = write_video(tmp_path / "odd.mp4", frames)
    assert read_video(p).shape == (5, 33, 47, 3)


def test_interrupted_write_leaves_nothing(tmp_path):
    p = tmp_path / "x.mp4"
    with pytest.raises(RuntimeError):
        with VideoWriter(p) as w:
            w.write(_frames()[0])
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_bad_frames_and_missing_file(tmp_path):
    with pytest.raises(GelsimError, match="uint8"):
        write_video(tmp_path / "a.mp4", [np.zeros((8, 8, 3), np.float32)])
    with pytest.raises(GelsimError, match="not found"):
        read_video(tmp_path / "nope.mp4")
    with pytest.raises(GelsimError, match="unknown video format"):
        video_path(tmp_path / "a", "gif")


def test_truncated_file_is_detected(tmp_path):
    p = write_video(tmp_path / "t.mp4", _frames(20))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    try:
        n = count_frames(p)
    except GelsimError:
        return
    assert n < 20
