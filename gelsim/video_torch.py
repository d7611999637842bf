"""RGB frames to the encoder's 4:2:0 planes on a torch device: the twin of OpenCV's ``COLOR_RGB2YUV_I420``
(what :meth:`gelsim.video.VideoWriter.write` runs on the host), so that ``--stages all`` brings its frames back as
I420 (half the bytes of RGB) and the host's CPU skips the conversion. Parity: ``tests/gelsim/test_video_torch.py``
(the same bytes as OpenCV's; the issue's bar was 1 DN).

OpenCV's conversion (measured bit for bit against its wheel, opencv-python 5.0 here): BT.601 limited range in
20-bit fixed point, luma from every pixel, each 2 x 2 block's chroma from its top-left pixel alone (no average).
"""
from __future__ import annotations

from . import batch_ops as ops

#: OpenCV's fixed-point BT.601 RGB -> YUV coefficients (its ``ITUR_BT_601_*`` constants, scaled by 2**SHIFT).
SHIFT = 20
R_Y, G_Y, B_Y = 269484, 528482, 102760
R_U, G_U, B_U = -155188, -305135, 460324
R_V, G_V, B_V = 460324, -385875, -74448
#: Limited range's offsets: luma from 16, chroma about 128 (8-bit codes).
Y_OFFSET, C_OFFSET = 16, 128


def rgb_to_i420(frames):
    """uint8 ``(B, H, W, 3)`` RGB frames (even H and W) on a device: uint8 ``(B, 3 H / 2, W)``, OpenCV's I420
    layout (the Y plane, then U's H/2 x W/2 samples, then V's, row-major), what ``cv2.cvtColor(frame,
    cv2.COLOR_RGB2YUV_I420)`` gives for each frame. Integer arithmetic in int32 (at most 2.6e8)."""
    torch = ops.torch_module()
    b, h, w, _ = frames.shape
    if h % 2 or w % 2:
        raise ValueError(f"I420 needs an even frame size, got {h} x {w}")
    x = frames.to(torch.int32)
    r, g, bl = x[..., 0], x[..., 1], x[..., 2]
    half = 1 << (SHIFT - 1)
    y = (R_Y * r + G_Y * g + B_Y * bl + (half + (Y_OFFSET << SHIFT))) >> SHIFT
    r, g, bl = r[:, ::2, ::2], g[:, ::2, ::2], bl[:, ::2, ::2]
    u = (R_U * r + G_U * g + B_U * bl + (half + (C_OFFSET << SHIFT))) >> SHIFT
    v = (R_V * r + G_V * g + B_V * bl + (half + (C_OFFSET << SHIFT))) >> SHIFT
    planes = [p.clamp(0, 255).to(torch.uint8).reshape(b, -1) for p in (y, u, v)]
    return torch.cat(planes, dim=1).reshape(b, h * 3 // 2, w)
