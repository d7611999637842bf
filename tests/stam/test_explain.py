"""stam.explain: Grad-CAM (Selvaraju et al. 2017) per frame, STAM's temporal attention map, explain()."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from stam.errors import StamError
from stam.explain import cv2_resize_nearest, explain, gradcam, temporal_map
from stam.models import build

N, CLASSES, SIZE = 3, 4, 96


def _model(name: str, seed: int = 0):
    torch.manual_seed(seed)
    m = build(name, N, CLASSES, width=0.25, image_size=SIZE, modules=3)
    m.train()                       # gradcam must switch it to eval (dropout off)
    return m


def _window(seed: int = 1) -> torch.Tensor:
    return torch.randn(1, N, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(seed))


def _gradcam_by_hand(model, x, target):
    """Grad-CAM from its definition: the class score's gradient with respect to the explained map A
    (backbone features; spatially attended ones when the model has spatial attention), averaged over
    each channel's positions, weighs A's channels; ReLU of the sum, upsampled bilinearly to the input,
    scaled by the maximum over the window's frames."""
    model.eval()
    f = model.frame_features(x).detach()
    a = (model.spatial(f.flatten(0, 1)).view_as(f) if model.spatial is not None else f).detach().requires_grad_(True)
    g = a if model.temporal is None else torch.stack([m(a) for m in model.temporal]).mean(0)
    score = model.classify(g)[0, target]
    (grad,) = torch.autograd.grad(score, a)
    alpha = grad.mean(dim=(3, 4), keepdim=True)
    cam = F.relu((alpha * a).sum(2))[0].detach()
    cam = F.interpolate(cam[:, None], size=x.shape[-2:], mode="bilinear", align_corners=False)[:, 0]
    return (cam / cam.max().clamp_min(1e-12)).numpy()


@pytest.mark.parametrize("name", ["cnn", "cnn_sa", "stam"])
def test_gradcam_is_the_definition(name):
    # An untrained model's ReLU map can be zero everywhere for the predicted class (every weighted
    # channel sum negative); take the first seed whose map is not, so that the scale is tested too.
    for seed in range(8):
        model, x = _model(name, seed), _window()
        cam, cls = gradcam(model, x)
        if cam.max() > 0:
            break
    assert not model.training
    with torch.no_grad():
        assert cls == int(model(x).argmax(1)[0])                  # default: the predicted class
    assert cam.shape == (N, SIZE, SIZE) and cam.dtype == np.float32
    assert cam.min() >= 0 and cam.max() == pytest.approx(1.0)   # one scale for the window's frames
    np.testing.assert_allclose(cam, _gradcam_by_hand(model, x, cls), rtol=1e-4, atol=1e-5)
    other = (cls + 1) % CLASSES
    cam2, cls2 = gradcam(model, x, target=other)
    assert cls2 == other
    np.testing.assert_allclose(cam2, _gradcam_by_hand(model, x, other), rtol=1e-4, atol=1e-5)


def test_temporal_map_averages_the_modules_row():
    model, x = _model("stam"), _window(2)
    tm = temporal_map(model, x)
    m = tm["map"]
    f = model.frame_features(x)
    f = model.spatial(f.flatten(0, 1)).view_as(f)
    _, n, _, h, w = f.shape
    assert m.shape == (n, h, w) and m.sum() == pytest.approx(1.0, abs=1e-5)   # a softmax row, averaged
    r, c = tm["query"]
    assert (r, c) == divmod(int(f[0, 0].norm(dim=0).argmax()), w)             # the strongest cell of frame 0
    with torch.no_grad():
        maps = torch.stack([mod(f, return_map=True)[1][0] for mod in model.temporal]).mean(0)
    np.testing.assert_allclose(m, maps[r * w + c].view(n, h, w).numpy(), rtol=1e-5, atol=1e-7)
    for t in range(n):
        top = [tuple(rc) for rc in tm["top3"][t]]
        assert len(top) == 3 and m[t][top[0]] == m[t].max() and m[t][top[0]] >= m[t][top[1]] >= m[t][top[2]]
    q = temporal_map(model, x, query=(0, 1))
    assert q["query"] == (0, 1)
    np.testing.assert_allclose(q["map"], maps[1].view(n, h, w).numpy(), rtol=1e-5, atol=1e-7)


def test_temporal_map_refuses_bad_input():
    with pytest.raises(StamError, match="no temporal attention"):
        temporal_map(_model("cnn_sa"), _window())
    with pytest.raises(StamError, match="outside"):
        temporal_map(_model("stam"), _window(), query=(99, 0))


def test_resize_nearest_keeps_square_cells():
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    up = cv2_resize_nearest(a, 6)
    assert up.shape == (6, 6)
    np.testing.assert_array_equal(up[:3, :2], 0.0)
    np.testing.assert_array_equal(up[3:, 4:], 5.0)


def test_explain_writes_files_and_refuses_bad_input(tiny_experiment, tmp_path):
    cells = tiny_experiment["out"] / "cells" / "clean"
    stam3, cnn3 = (str(cells / "n3" / m / "seed0" / "best.pt") for m in ("stam", "cnn"))
    res = explain([cnn3], out=tmp_path / "cnn")
    assert res["files"] == [str(tmp_path / "cnn" / "gradcam.png")] and "temporal_query" not in res
    seq = res["sequence"]
    both = explain([cnn3, stam3], sequence=seq, out=tmp_path / "both")
    assert both["sequence"] == seq and set(both["predictions"]) == {"cnn", "stam"}
    assert [p.rsplit("/", 1)[1] for p in both["files"]] == ["gradcam.png", "temporal.png"]
    assert all((tmp_path / "both" / f).stat().st_size > 1000 for f in ("gradcam.png", "temporal.png"))
    assert not list((tmp_path / "both").glob(".*partial*"))
    with pytest.raises(StamError, match="no checkpoint"):
        explain([], out=tmp_path)
    with pytest.raises(StamError, match="differ in frames"):
        explain([stam3, str(cells / "n2" / "stam" / "seed0" / "best.pt")], out=tmp_path)
    with pytest.raises(StamError, match="is not in the test split"):
        explain([cnn3], sequence="f999-s9999", out=tmp_path)
