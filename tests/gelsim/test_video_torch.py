"""gelsim.video_torch: the device's RGB -> I420 conversion gives OpenCV's planes byte for byte (the issue's bar was
1 DN), and the writer given those planes (gelsim.video.I420) writes the same file as given the RGB frames."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.errors import GelsimError  # noqa: E402
from gelsim.video import I420, VideoWriter, video_path, write_video  # noqa: E402
from gelsim.video_torch import rgb_to_i420  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]


def _frames(n: int, h: int, w: int) -> np.ndarray:
    """Noise over the whole code range (every coefficient's product and the rounding at its edges) and a smooth
    gradient with a dark square (a tactile frame's content): uint8 (n, h, w, 3)."""
    rng = np.random.default_rng(3)
    out = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    out[0] = np.stack([60 + xx // 4, 80 + yy // 3, 120 + (xx + yy) // 8], -1).clip(0, 255)
    out[0, 10:20, 5:15] = 20
    out[1] = 0
    out[2] = 255
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("h, w", [(48, 64), (720, 960)])
def test_i420_matches_opencv(device, h, w):
    frames = _frames(4, h, w)
    got = rgb_to_i420(torch.as_tensor(frames, device=device)).cpu().numpy()
    ref = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2YUV_I420) for f in frames])
    assert got.shape == ref.shape == (4, h * 3 // 2, w) and got.dtype == np.uint8
    assert np.array_equal(got, ref)
    # the comparison sees a chroma taken from another pixel of its block (an average, or the bottom-right)
    moved = frames.copy()
    moved[:, ::2, ::2] = frames[:, 1::2, 1::2]
    assert not np.array_equal(rgb_to_i420(torch.as_tensor(moved, device=device)).cpu().numpy(), ref)


def test_writer_takes_i420_the_same_file(tmp_path):
    frames = _frames(5, 48, 128)
    rgb = write_video(tmp_path / "rgb.mp4", list(frames))
    planes = rgb_to_i420(torch.as_tensor(frames)).numpy()
    with VideoWriter(tmp_path / "yuv.mp4") as writer:
        for p in planes:
            writer.write(I420(p))
    assert rgb.read_bytes() == (tmp_path / "yuv.mp4").read_bytes()


@pytest.mark.parametrize("fmt, h, w", [("png", 48, 64), ("ffv1", 48, 64), ("h264", 33, 47)])
def test_i420_refused_where_the_video_is_not_420(tmp_path, fmt, h, w):
    planes = np.zeros((h * 3 // 2, w), np.uint8)
    with pytest.raises(GelsimError, match="I420 frame goes to an H.264 video of even size"):
        with VideoWriter(video_path(tmp_path / "v", fmt), fmt=fmt) as writer:
            writer.write(I420(planes))
    assert not list(tmp_path.iterdir())
