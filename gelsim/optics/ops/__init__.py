"""The optics' primitives, one module each, with their numpy kernel and their torch kernel side by side.

Each module holds one primitive of the renderer in two kernels of the same semantics: the numpy one
(OpenCV and numba in float32, as tuned for the CPU: the numpy backend's frames are the bit-exact
reference) and the torch one (``..._torch``, batched over ``B`` frames as ``(B, ..., H, W)`` tensors, on
any device). ``tests/gelsim/test_optics_ops.py`` checks each pair op by op on random inputs against a
stated tolerance, so that a change of either kernel is caught where it is made. The backends compose
these primitives (:mod:`gelsim.optics.composite`: the order of the optics, written once); no kernel
reads another backend's state.

* :mod:`.filters`: the camera blur and other Gaussian blurs, Sobel slopes, per-pixel channel mixes;
* :mod:`.resample`: area averages by a whole factor, bilinear upsampling by one;
* :mod:`.box`: the box around an imprint that the shading covers;
* :mod:`.phong`: Lambert + Phong shading change under the profile's LEDs;
* :mod:`.table`: the calibrated table's lookup at the membrane's normal;
* :mod:`.shadows`: the LEDs' soft shadows;
* :mod:`.coarse`: the table's depth and halo terms;
* :mod:`.markers`: the markers' anti-aliased, blurred darkening;
* :mod:`.readout`: camera noise and 8-bit quantisation.

Torch is optional (the numpy backend does not import it): the torch kernels import it when called.
Their frames are the same bytes for any batch size and on any device: a pixel comes from element-wise
IEEE operations, exact copies (gathers, padding, slicing) and order-free reductions (max), each over
its own frame; filters are sums of shifted slices in a fixed order, not convolutions (whose algorithm
and summation order a library may choose by the batch's shape).
"""
from __future__ import annotations

from ...errors import GelsimError


def torch_module():
    """The torch module, or one line saying how to get it."""
    try:
        import torch
    except ImportError:  # torch is installed by `make install`; a bare `pip install gelsim` lacks it
        raise GelsimError("the torch backend needs PyTorch; install it (make install, or pip install torch)") from None
    return torch


def pad_hw(x, pad: tuple[int, int, int, int], mode: str):
    """``x`` (``(..., H, W)`` tensor) padded by ``pad`` = (left, right, top, bottom) px, ``mode``
    ``"replicate"`` or ``"constant"`` (zero): exact copies, whatever the leading dimensions."""
    torch = torch_module()
    h, w = x.shape[-2:]
    xp = torch.nn.functional.pad(x.reshape(-1, 1, h, w), pad, mode=mode)
    return xp.reshape(*x.shape[:-2], *xp.shape[-2:])
