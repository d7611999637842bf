import numpy as np
import pytest
import torch

from gelsim.errors import GelsimError
from stam import models
from stam.models import SpatialAttention, TemporalAttention, build


def _conv2d_direct(x, weight, bias):
    """x: (Cin, H, W), weight (Cout, Cin, k, k), zero padding k//2, stride 1, by loops."""
    cin, h, w = x.shape
    cout, _, k, _ = weight.shape
    p = k // 2
    xp = np.zeros((cin, h + 2 * p, w + 2 * p))
    xp[:, p:p + h, p:p + w] = x
    out = np.zeros((cout, h, w))
    for o in range(cout):
        for i in range(h):
            for j in range(w):
                out[o, i, j] = (xp[:, i:i + k, j:j + k] * weight[o]).sum() + (bias[o] if bias is not None else 0)
    return out


def test_spatial_attention_matches_eq1():
    torch.manual_seed(0)
    sa = SpatialAttention().double()
    x = torch.randn(2, 5, 6, 7, dtype=torch.float64)
    y = sa(x).detach().numpy()
    w, b = sa.conv.weight.detach().numpy(), sa.conv.bias.detach().numpy()
    for n in range(2):
        xn = x[n].numpy()
        desc = np.stack([xn.max(0), xn.mean(0)])  # [MaxPool; AvgPool] over channels
        a = 1 / (1 + np.exp(-_conv2d_direct(desc, w, b)))  # (1, H, W)
        np.testing.assert_allclose(sa.last_map[n].numpy(), a, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(y[n], a * xn, rtol=1e-10, atol=1e-12)
    assert y.shape == (2, 5, 6, 7)


def _temporal_direct(x, ta, gain):
    """Eq. 2-3 by explicit loops over the m = n*h*w positions of one window x (n, C, h, w)."""
    n, c, h, w = x.shape
    pos = [x[t, :, r, s] for t in range(n) for r in range(h) for s in range(w)]  # m vectors of C
    lin = lambda conv, v: conv.weight.detach().numpy()[:, :, 0, 0, 0] @ v + conv.bias.detach().numpy()
    q = [lin(ta.q, p) for p in pos]
    k = [lin(ta.k, p) for p in pos]
    v = [lin(ta.v, p) for p in pos]
    m = len(pos)
    a = np.zeros((m, m))
    out = []
    for j in range(m):
        s = np.array([q[i] @ k[j] for i in range(m)])  # s_ij for all i
        a[j] = np.exp(s) / np.exp(s).sum()
        out.append(gain * sum(a[j, i] * v[i] for i in range(m)) + pos[j])
    y = np.zeros_like(x)
    idx = 0
    for t in range(n):
        for r in range(h):
            for s_ in range(w):
                y[t, :, r, s_] = out[idx]
                idx += 1
    return y, a


@pytest.mark.parametrize("gain_mode", ["fixed", "learned"])
def test_temporal_attention_matches_eq2_eq3(gain_mode):
    torch.manual_seed(1)
    ta = TemporalAttention(6, qk_reduction=2, residual_gain=gain_mode).double()
    gain = 1.0
    if gain_mode == "learned":
        assert ta.gamma.item() == 0.0
        with torch.no_grad():
            ta.gamma.fill_(0.7)
        gain = 0.7
    x = torch.randn(2, 3, 6, 2, 3, dtype=torch.float64)
    y, a = ta(x, return_map=True)
    assert y.shape == x.shape and a.shape == (2, 18, 18)
    np.testing.assert_allclose(a.detach().sum(-1).numpy(), 1.0, rtol=1e-12)
    for b in range(2):
        y_ref, a_ref = _temporal_direct(x[b].numpy(), ta, gain)
        np.testing.assert_allclose(a[b].detach().numpy(), a_ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(y[b].detach().numpy(), y_ref, rtol=1e-9, atol=1e-12)


def test_temporal_attention_starts_as_identity_with_learned_gain():
    ta = TemporalAttention(8)
    x = torch.randn(1, 4, 8, 3, 3)
    assert torch.equal(ta(x), x)


def test_temporal_attention_is_frame_permutation_equivariant():
    torch.manual_seed(2)
    ta = TemporalAttention(8, residual_gain="fixed")
    x = torch.randn(1, 4, 8, 2, 2)
    perm = torch.tensor([2, 0, 3, 1])
    torch.testing.assert_close(ta(x)[:, perm], ta(x[:, perm]), rtol=1e-5, atol=1e-6)


def _keep(b, n):
    """A keep mask for the oracle: window i keeps its last i % n + 1 frames."""
    return torch.stack([torch.arange(n) >= n - 1 - i % n for i in range(b)])


@pytest.mark.parametrize("name", models.MODELS)
def test_output_shapes_for_n_2_to_7(name):
    torch.manual_seed(0)
    for n in range(2, 8):
        m = build(name, n, 5, width=0.125, image_size=96).eval()
        keep = (_keep(2, n),) if m.needs_onset else ()
        with torch.no_grad():
            assert m(torch.randn(2, n, 3, 96, 96), *keep).shape == (2, 5)
        with pytest.raises(GelsimError):
            m(torch.randn(2, n + 1, 3, 96, 96), *keep)


@pytest.mark.parametrize("name", models.MODELS)
@pytest.mark.parametrize("options", [{}, {"fusion": "mean_features", "combine": "concat", "sa_batchnorm": True}])
def test_gradients_reach_every_parameter(name, options):
    torch.manual_seed(0)
    if name in models.VARIANTS and "fusion" in models.VARIANTS[name][1]:
        options = {k: v for k, v in options.items() if k != "fusion"}   # the variant fixes its fusion
    m = build(name, 3, 4, width=0.125, image_size=96, dropout=0.0, **options)
    if m.temporal is not None:  # at gamma = 0 no gradient reaches q and k, by design: move off it
        with torch.no_grad():
            for t in m.temporal:
                t.gamma.fill_(0.5)
    m.train()
    keep = (_keep(3, 3),) if m.needs_onset else ()
    loss = torch.nn.functional.cross_entropy(m(torch.randn(3, 3, 3, 96, 96), *keep), torch.tensor([0, 1, 2]))
    loss.backward()
    missing = [k for k, p in m.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert not missing, missing


def test_parameter_counts_at_paper_setting():
    cnn = models.parameter_count("cnn", 2, 100)
    assert cnn == 57_413_540  # AlexNet with a 100-class head: the paper's 57.4 M
    assert round(cnn / 1e6, 1) == models.PAPER_PARAMS["cnn"] / 1e6
    assert models.parameter_count("cnn", 7, 100) == cnn  # parameter-free fusion
    assert models.parameter_count("cnn_sa", 2, 100) == cnn + 2 * 49 + 1
    per_module = 2 * (256 * 32 + 32) + (256 * 256 + 256) + 1
    assert models.parameter_count("stam", 2, 100) == cnn + 99 + 10 * per_module
    readings = models.paper_readings()
    assert min(abs(r["params"] - 68.8e6) for r in readings) < 0.05e6


def test_build_rejects_bad_options():
    for kwargs in ({"name": "vgg"}, {"fusion": "sum"}, {"combine": "max"}):
        args = {"name": "stam", "n_frames": 2, "num_classes": 3, "width": 0.125, "image_size": 96} | kwargs
        with pytest.raises(GelsimError):
            build(**args)


def test_fold_batchnorm_gives_the_same_plain_alexnet():
    from stam.backbone import AlexNetFeatures, fold_batchnorm

    torch.manual_seed(0)
    bn = AlexNetFeatures(0.25, batchnorm=True)
    bn.train()
    for _ in range(3):  # give the running statistics non-trivial values
        bn(torch.randn(4, 3, 96, 96) * 2 + 0.5)
    for m in bn.features:
        if isinstance(m, torch.nn.BatchNorm2d):
            torch.nn.init.uniform_(m.weight, 0.5, 1.5)
            torch.nn.init.uniform_(m.bias, -0.2, 0.2)
    bn.eval()
    plain = fold_batchnorm(bn)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in plain.modules())
    assert set(plain.state_dict()) == set(AlexNetFeatures(0.25).state_dict())
    x = torch.randn(2, 3, 96, 96)
    assert torch.allclose(plain(x), bn(x), atol=1e-4, rtol=1e-4)


def test_attention_at_conv5_reads_the_map_before_the_last_pool():
    from stam.backbone import feature_size

    assert (feature_size(128), feature_size(128, "conv5")) == (3, 7)
    assert (feature_size(224), feature_size(224, "conv5")) == (6, 13)
    torch.manual_seed(0)
    x = torch.randn(2, 3, 3, 128, 128)
    # The CNN is the same function at both cuts (the pool moves from the backbone to the head's input).
    a = build("cnn", 3, 7, width=0.125, image_size=128, hidden=32).eval()
    b = build("cnn", 3, 7, width=0.125, image_size=128, hidden=32, attention_at="conv5").eval()
    b.load_state_dict(a.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(a(x), b(x), rtol=0, atol=0)
        assert b.frame_features(x).shape == (2, 3, 32, 7, 7)   # 256 x 0.125 channels
    # With attention the two differ: the spatial map has 7 x 7 positions at conv5, 3 x 3 at pool5.
    sa5 = build("cnn_sa", 3, 7, width=0.125, image_size=128, hidden=32, attention_at="conv5").eval()
    sa = build("cnn_sa", 3, 7, width=0.125, image_size=128, hidden=32).eval()
    with torch.no_grad():
        sa5(x), sa(x)
    assert sa5.spatial.last_map.shape == (6, 1, 7, 7) and sa.spatial.last_map.shape == (6, 1, 3, 3)
    st = build("stam", 3, 7, width=0.125, image_size=128, hidden=32, attention_at="conv5").eval()
    with torch.no_grad():
        assert st(x).shape == (2, 7)
    assert st.temporal[0].last_map.shape == (2, 3 * 49, 3 * 49)
    with pytest.raises(GelsimError, match="attention_at"):
        build("cnn", 2, 3, width=0.125, image_size=96, attention_at="fc6")


def test_stam_paper_parameter_count_at_paper_size():
    """The paper's STAM (n = 2, 224 px, 100 classes) has 68.8 M parameters. stam_paper: AlexNet (57,413,540),
    spatial attention (99), ten modules with q, k, v all 256 -> 256 and a gain (197,377 each), one FC on the
    flattened attended window, 2 x 256 x 6 x 6 = 18,432 -> 512 (9,437,696), whose 512 outputs join the
    frames' mean fc7 output in fc8 (512 x 100 more weights; fc8's bias serves both): 68,876,305. Tolerance
    0.1 M: the count is 0.08 M above the printed 68.8 (68.88 rounds to 68.9; the paper may have truncated,
    or left the final 51,200 weights out); no reading without such a dense layer comes within 9 M."""
    alexnet = 57_413_540
    module = 3 * (256 * 256 + 256) + 1
    window = 18_432 * 512 + 512
    count = models.parameter_count("stam_paper", 2, 100)
    assert count == alexnet + 99 + 10 * module + window + 512 * 100 == 68_876_305
    assert abs(count - models.PAPER_PARAMS["stam_paper"]) < 0.1e6
    # the same head without attention, and the FC alone (no per-frame head)
    assert models.parameter_count("cnn_joint", 2, 100) == alexnet + window + 512 * 100
    conv = alexnet - (9216 * 4096 + 4096) - (4096 * 4096 + 4096) - (4096 * 100 + 100)
    assert models.parameter_count("cnn_flatten", 2, 100) == conv + window + 512 * 100 + 100
    # the window layer grows with n: 7 frames at the cpu preset's size (128 x 3 x 3 per frame)
    small = dict(width=0.5, image_size=128, hidden=512)
    assert (models.parameter_count("cnn_joint", 7, 100, **small) - models.parameter_count("cnn", 7, 100, **small)
            == 7 * 128 * 9 * 512 + 512 + 512 * 100)
    assert models.parameter_count("oracle", 2, 100) == alexnet   # the oracle's fusion has no weights


def _permuted(model, n=4, b=2, keep=None):
    x = torch.randn(b, n, 3, 96, 96)
    perm = torch.tensor([2, 0, 3, 1])
    with torch.no_grad():
        return model(x, *keep or ()), model(x[:, perm], *keep or ())


@pytest.mark.parametrize("name,sees_order", [("cnn", False), ("cnn_mean_features", False), ("cnn_max_features", False),
                                             ("stam", False), ("cnn_flatten", True), ("cnn_joint", True),
                                             ("stam_paper", True)])
def test_which_models_see_the_frames_order(name, sees_order):
    """Averages and maxima over frames, and the temporal attention (equivariant), give the same logits
    for any order of the window's frames; a head with weights per frame position does not."""
    torch.manual_seed(3)
    m = build(name, 4, 6, width=0.125, image_size=96, hidden=32, window_hidden=16).eval()
    if m.temporal is not None:
        with torch.no_grad():
            for t in m.temporal:
                t.gamma.fill_(0.7)
    a, b = _permuted(m)
    if sees_order:
        assert (a - b).abs().max() > 1e-4
    else:
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_oracle_averages_the_kept_frames_only():
    torch.manual_seed(4)
    m = build("oracle", 4, 5, width=0.125, image_size=96, hidden=32).eval()
    x = torch.randn(3, 4, 3, 96, 96)
    keep = torch.tensor([[False, False, True, True], [True, True, True, True], [False, False, False, True]])
    with torch.no_grad():
        per_frame = m.head(m.frame_features(x).flatten(0, 1)).view(3, 4, 5)
        out = m(x, keep)
        for i in range(3):
            torch.testing.assert_close(out[i], per_frame[i][keep[i]].mean(0))
        # what the dropped frames show does not matter
        y = x.clone()
        y[0, :2] = torch.randn(2, 3, 96, 96) * 5
        y[2, :3] = 0
        torch.testing.assert_close(m(y, keep)[[0, 2]], out[[0, 2]])
        # keeping every frame is the CNN with the same weights
        cnn = build("cnn", 4, 5, width=0.125, image_size=96, hidden=32).eval()
        cnn.load_state_dict(m.state_dict())
        torch.testing.assert_close(m(x, torch.ones(3, 4, dtype=torch.bool)), cnn(x))
    with pytest.raises(GelsimError, match="keep mask"):
        m(x)


def test_variants_fix_their_options():
    arch, opts = models.variant("stam_paper", {"qk_reduction": 8, "fusion": "mean_logits", "width": 0.5})
    assert arch == "stam" and opts == {"qk_reduction": 1, "fusion": "joint", "width": 0.5}
    assert models.variant("cnn", {"fusion": "max_features"}) == ("cnn", {"fusion": "max_features"})
    with pytest.raises(GelsimError, match="stam_paper is stam with qk_reduction = 1"):
        build("stam_paper", 2, 3, width=0.125, image_size=96, qk_reduction=4)
    with pytest.raises(GelsimError, match="unknown"):
        build("resnet", 2, 3)
    m = build("stam_paper", 2, 3, width=0.125, image_size=96)
    assert m.name == "stam" and m.variant == "stam_paper" and m.fusion == "joint"
    assert m.temporal[0].q.out_channels == m.backbone.out_channels


def test_a_variants_config_says_what_was_trained():
    from stam.config import TrainConfig, resolve_train

    cfg = resolve_train(TrainConfig(), {"model": "oracle"})
    assert cfg.fusion == "onset" and cfg.model == "oracle"
    assert resolve_train(TrainConfig(), {"model": "stam_paper"}).qk_reduction == 1
    with pytest.raises(GelsimError, match="cnn_joint is cnn with fusion"):
        resolve_train(TrainConfig(), {"model": "cnn_joint", "fusion": "max_features"})
    # the config's defaults are build()'s, so that a default is never read as a choice
    for k, v in TrainConfig().model_options().items():
        if k in models.BUILD_DEFAULTS:
            assert models.BUILD_DEFAULTS[k] == v, k
