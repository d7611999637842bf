"""The three models of the paper's ablation: CNN baseline, CNN + spatial attention, STAM.

Every model takes a batch of tactile windows ``B x n x 3 x S x S`` (float, normalised
as in :mod:`stam.data`) and returns class logits ``B x num_classes``. Each frame goes
through the same AlexNet feature extractor (``F``: ``C x h x w``, cut at the last
max-pool); then

* ``cnn``:    F -> per-frame AlexNet head (fc6-fc8) -> fusion over the n frames;
* ``cnn_sa``: F -> spatial attention (Eq. 1) -> head -> fusion;
* ``stam``:   F -> spatial attention -> ``modules`` temporal attention blocks in
  parallel over all n*h*w positions (Eq. 2-3), combined -> head -> fusion.

Choices the paper leaves open (each an option of :func:`build`, argued in docs/stam.md):

* ``fusion`` of the n frames: ``mean_logits`` (default; average of per-frame class
  scores, parameter-free, so the baseline has exactly AlexNet's 57.4 M parameters as
  the paper reports), ``mean_features`` (average the feature maps before fc6),
  ``max_features``, or, position-aware (:class:`WindowHead`: one fully connected layer on the
  flattened ``n x C x h x w`` window, so each frame's position has weights of its own):
  ``flatten`` (that layer, ReLU, then a class layer: no per-frame head) or ``joint`` (the
  per-frame head's fc7 outputs averaged over the frames and that layer's output, concatenated,
  into fc8: the reading of the paper's 68.8 M parameters, docs/stam.md). ``onset`` is the
  onset-aware oracle's: ``mean_logits`` over the frames from the detected contact onset on only
  (a ``keep`` mask per window, :mod:`stam.oracle`).
* ``combine`` of the parallel temporal modules: ``mean`` (default, parameter-free; the
  paper averages the modules' attention maps for Fig. 7, so averaging their outputs is
  the closest reading) or ``concat`` (channel concatenation then a 1x1x1 projection back
  to C, as multi-head attention does).
* ``qk_reduction``: q and k have C / qk_reduction channels (default 8, as SAGAN); v keeps C.
* ``residual_gain``: ``learned`` (default; SAGAN's gamma * A v + x with gamma starting at 0,
  so STAM starts as exactly CNN + SA on the same pretrained weights) or ``fixed``
  (Eq. 3 verbatim: A v + x).
* ``sa_batchnorm``: the official CBAM code puts BatchNorm after the 7x7 conv; the paper's
  Eq. 1 has none (default False).
* ``attention_at``: ``pool5`` (default; the paper's F, after the last max-pool) or ``conv5``:
  the attention reads conv5's map, before that pool, and the pool follows it (so the CNN is the
  same function at both). At 128 px that is 7 x 7 positions per frame instead of 3 x 3, about the
  paper's 6 x 6 at 224 px; a diagnostic of the cpu preset's small map (docs/stam.md).
* ``window_hidden``: the output width of the position-aware fusions' layer on the flattened
  window (512, the paper's count's reading).

Named variants (:data:`VARIANTS`) fix some of these options under a name of their own, so that a
sweep can hold several settings of one architecture side by side: e.g. ``stam_paper`` (full-width
q, k, v and the ``joint`` head), ``cnn_joint`` (the same head without attention), ``oracle``.
"""
from __future__ import annotations

import inspect

import torch
import torch.nn.functional as F
from torch import nn

from gelsim.errors import check_choice

from .backbone import CUTS, AlexNetFeatures, AlexNetHead, feature_size
from .errors import StamError

MODEL_NAMES = ("cnn", "cnn_sa", "stam")   # the architectures
FUSIONS = ("mean_logits", "mean_features", "max_features", "flatten", "joint", "onset")
# Fusions whose head has weights per frame position (it can learn to discount the first frame).
POSITION_AWARE = ("flatten", "joint")
# Named variants: an architecture with some options fixed (what `stam experiment --models` and
# `stam train --model` accept besides the architectures). The study of issue 48 needs them side by
# side in one sweep: the baseline's fusions, the position-aware head with and without attention, the
# paper's STAM as its parameter count reads (docs/stam.md), and the onset-aware oracle.
VARIANTS = {
    "cnn_mean_features": ("cnn", {"fusion": "mean_features"}),
    "cnn_max_features": ("cnn", {"fusion": "max_features"}),
    "cnn_flatten": ("cnn", {"fusion": "flatten"}),
    "cnn_joint": ("cnn", {"fusion": "joint"}),
    "stam_paper": ("stam", {"qk_reduction": 1, "fusion": "joint"}),
    "oracle": ("cnn", {"fusion": "onset"}),
}
MODELS = MODEL_NAMES + tuple(VARIANTS)
COMBINES = ("mean", "concat")
RESIDUAL_GAINS = ("learned", "fixed")
# Paper's reported parameter counts (Sec. IV-B), at full AlexNet, 224 px, 100 classes, n = 2
# (stam_paper is the reading of the STAM count, docs/stam.md).
PAPER_PARAMS = {"cnn": 57.4e6, "stam": 68.8e6, "stam_paper": 68.8e6}


class SpatialAttention(nn.Module):
    """Eq. 1: ``A_S(F) = sigmoid(conv7x7([MaxPool_c(F); AvgPool_c(F)]))``, output ``A_S(F) * F``.

    Input and output ``B x C x H x W``; the map ``A_S`` is ``B x 1 x H x W`` in (0, 1).
    The pooling runs over the channel axis; the 7x7 convolution is zero-padded by 3.
    """

    def __init__(self, kernel_size: int = 7, batchnorm: bool = False):
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel_size, padding=kernel_size // 2, bias=not batchnorm)
        self.bn = nn.BatchNorm2d(1) if batchnorm else nn.Identity()
        self.last_map: torch.Tensor | None = None  # kept for stam.explain

    def attention_map(self, x: torch.Tensor) -> torch.Tensor:
        """``B x 1 x H x W`` spatial attention map of ``x`` (``B x C x H x W``)."""
        desc = torch.cat([x.amax(dim=1, keepdim=True), x.mean(dim=1, keepdim=True)], dim=1)
        return torch.sigmoid(self.bn(self.conv(desc)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.attention_map(x)
        self.last_map = a.detach()
        return a * x


class TemporalAttention(nn.Module):
    """Eq. 2-3: self-attention over all ``m = n*h*w`` positions of a window.

    Input and output ``B x n x C x h x w``. q, k, v are 1x1x1 convolutions (per-position
    linear maps) to ``C/qk_reduction``, ``C/qk_reduction`` and ``C`` channels. With
    ``s_ij = q(F_i) . k(F_j)``, the map ``A[j, i] = softmax_i(s_ij)`` (each row j sums to 1
    over the keys i) and ``F^T_j = gain * sum_i A[j, i] v(F_i) + F_j``, where gain is a
    learned scalar starting at ``gamma_init`` (``residual_gain="learned"``) or 1 (``"fixed"``,
    Eq. 3 as printed). No 1/sqrt(d) scaling, as in the paper and SAGAN.
    """

    def __init__(self, channels: int, qk_reduction: int = 8, residual_gain: str = "learned",
                 gamma_init: float = 0.0):
        super().__init__()
        check_choice("residual_gain", residual_gain, RESIDUAL_GAINS, StamError)
        cq = max(1, channels // qk_reduction)
        self.q = nn.Conv3d(channels, cq, kernel_size=1)
        self.k = nn.Conv3d(channels, cq, kernel_size=1)
        self.v = nn.Conv3d(channels, channels, kernel_size=1)
        self.gamma = nn.Parameter(torch.tensor(float(gamma_init))) if residual_gain == "learned" else None
        self.last_map: torch.Tensor | None = None  # B x m x m, kept for stam.explain

    def forward(self, x: torch.Tensor, return_map: bool = False):
        b, n, c, h, w = x.shape
        # Positions ordered (frame, row, col), channels last: B x m x C. A 1x1x1 convolution is a
        # per-position linear map; F.linear with the Conv3d weights computes exactly that, several
        # times faster than CPU Conv3d on these small maps.
        xm = x.permute(0, 1, 3, 4, 2).reshape(b, n * h * w, c)
        q = F.linear(xm, self.q.weight.flatten(1), self.q.bias)  # B x m x Cq
        k = F.linear(xm, self.k.weight.flatten(1), self.k.bias)
        v = F.linear(xm, self.v.weight.flatten(1), self.v.bias)  # B x m x C
        s = torch.bmm(k, q.transpose(1, 2))  # s[b, j, i] = k_j . q_i = s_ij of Eq. 2
        a = torch.softmax(s, dim=2)  # normalised over the keys i
        out = torch.bmm(a, v)  # out[:, j] = sum_i A[j, i] v_i
        if self.gamma is not None:
            out = self.gamma * out
        out = out.view(b, n, h, w, c).permute(0, 1, 4, 2, 3) + x
        self.last_map = a.detach()
        return (out, a) if return_map else out


class WindowHead(nn.Module):
    """One fully connected layer on a whole window, flattened: ``B x n x C x h x w`` ->
    ``B x hidden`` (dropout, linear, ReLU, dropout). Frame t's features meet weights of their own,
    so the layer sees each frame's position in the window (unlike any average over frames). At the
    paper's size (n = 2, 256 x 6 x 6 per frame) it is 18,432 -> 512: 9.44 M parameters."""

    def __init__(self, in_features: int, hidden: int, dropout: float = 0.5):
        super().__init__()
        self.layer = nn.Sequential(nn.Dropout(dropout), nn.Linear(in_features, hidden), nn.ReLU(inplace=True),
                                   nn.Dropout(dropout))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.layer(f.flatten(1))


def variant(name: str, options: dict | None = None) -> tuple[str, dict]:
    """(architecture, options) of a model name: an architecture keeps ``options``; a named variant
    (:data:`VARIANTS`) sets its fixed options. An option given with another value than the variant's
    and than :func:`build`'s default is an error (the name would not say what was trained)."""
    options = dict(options or {})
    if name in MODEL_NAMES:
        return name, options
    if name not in VARIANTS:
        raise StamError(f"model {name!r} unknown; choose one of {', '.join(MODELS)}")
    arch, fixed = VARIANTS[name]
    for k, v in fixed.items():
        given = options.get(k, v)
        if given != v and given != BUILD_DEFAULTS[k]:
            raise StamError(f"model {name} is {arch} with {k} = {v!r}, but {k} = {given!r} was asked for; "
                            f"use model {arch} with that {k}, or leave {k} at its default")
        options[k] = v
    return arch, options


class SequenceModel(nn.Module):
    """Shared frame: per-frame AlexNet features -> optional attention -> head -> fusion."""

    def __init__(self, name: str, n_frames: int, num_classes: int, *, width: float = 1.0,
                 image_size: int = 224, fusion: str = "mean_logits", modules: int = 10,
                 combine: str = "mean", qk_reduction: int = 8, residual_gain: str = "learned",
                 sa_batchnorm: bool = False, dropout: float = 0.5, pool: int | None = None,
                 hidden: int = 0, attention_at: str = "pool5", window_hidden: int = 512):
        super().__init__()
        check_choice("model", name, MODEL_NAMES, StamError)
        check_choice("attention_at", attention_at, CUTS, StamError)
        check_choice("fusion", fusion, FUSIONS, StamError)
        check_choice("combine", combine, COMBINES, StamError)
        if n_frames < 1:
            raise StamError(f"n_frames must be at least 1, got {n_frames}; use 2..7 as the paper")
        if modules < 1 or qk_reduction < 1:
            raise StamError("modules and qk_reduction must be at least 1; use the defaults 10 and 8")
        if window_hidden < 1:
            raise StamError(f"window_hidden must be at least 1, got {window_hidden}; use 512, the paper's reading")
        fs = feature_size(image_size)
        if fs < 1:
            raise StamError(f"image_size {image_size} px is too small for AlexNet; use at least 64")
        self.name, self.n_frames, self.num_classes, self.fusion = name, n_frames, num_classes, fusion
        self.variant = name
        self.combine = combine
        self.backbone = AlexNetFeatures(width, cut=attention_at)
        # conv5's map is pooled as the backbone's last layer would have, after the attention
        self.pool5 = nn.MaxPool2d(kernel_size=3, stride=2) if attention_at == "conv5" else None
        c = self.backbone.out_channels
        self.spatial = SpatialAttention(batchnorm=sa_batchnorm) if name in ("cnn_sa", "stam") else None
        if name == "stam":
            self.temporal = nn.ModuleList(
                TemporalAttention(c, qk_reduction, residual_gain) for _ in range(modules))
            self.project = nn.Conv3d(c * modules, c, kernel_size=1) if combine == "concat" else None
        else:
            self.temporal, self.project = None, None
        # Pool to the backbone's own map size unless told: 6 x 6 at 224 px (torchvision's value).
        # ``flatten`` has no per-frame head; the other fusions do.
        self.head = (None if fusion == "flatten" else
                     AlexNetHead(c, num_classes, width, pool or fs, dropout, hidden or None))
        self.window, self.window_out = None, None
        if fusion in POSITION_AWARE:
            self.window = WindowHead(n_frames * c * fs * fs, window_hidden, dropout)
            # joint: fc8 reads [mean over frames of fc7 ; the window's features]. fc8 is linear, so that is
            # fc8(mean fc7) + W x window: the mean of the per-frame logits plus a layer without bias (fc8's
            # bias serves both). flatten: a class layer of its own.
            self.window_out = nn.Linear(window_hidden, num_classes, bias=fusion == "flatten")

    @property
    def needs_onset(self) -> bool:
        """Whether forward needs each window's ``keep`` mask (the oracle's fusion, :mod:`stam.oracle`)."""
        return self.fusion == "onset"

    def frame_features(self, x: torch.Tensor) -> torch.Tensor:
        """``B x n x 3 x S x S`` images -> ``B x n x C x h x w`` backbone features."""
        b, n = x.shape[:2]
        f = self.backbone(x.flatten(0, 1))
        return f.view(b, n, *f.shape[1:])

    def attend(self, f: torch.Tensor) -> torch.Tensor:
        """Attention part on backbone features; ``B x n x C x h x w`` in and out."""
        b, n = f.shape[:2]
        if self.spatial is not None:
            f = self.spatial(f.flatten(0, 1)).view_as(f)
        if self.temporal is not None:
            outs = [m(f) for m in self.temporal]
            if self.project is None:
                f = torch.stack(outs, 0).mean(0)
            else:
                cat = torch.cat(outs, 2).permute(0, 2, 1, 3, 4)  # B x (C*M) x n x h x w
                f = self.project(cat).permute(0, 2, 1, 3, 4)
        return f

    def classify(self, f: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """Head and fusion: attended ``B x n x C x h x w`` -> ``B x num_classes`` logits. ``keep``
        (``bool B x n``; the ``onset`` fusion only, where it is required): the frames whose logits
        are averaged."""
        b, n = f.shape[:2]
        if self.pool5 is not None:
            f = self.pool5(f.flatten(0, 1))
            f = f.view(b, n, *f.shape[1:])
        if self.fusion == "flatten":
            return self.window_out(self.window(f))
        if self.fusion in ("mean_features", "max_features"):
            return self.head(f.mean(1) if self.fusion == "mean_features" else f.amax(1))
        per_frame = self.head(f.flatten(0, 1)).view(b, n, -1)
        if self.fusion == "joint":
            return per_frame.mean(1) + self.window_out(self.window(f))
        if self.fusion == "onset":
            if keep is None:
                raise StamError("the onset fusion (the oracle) needs each window's keep mask; "
                                "give it the windows of stam.oracle.OnsetWindows")
            w = keep.to(per_frame.dtype).unsqueeze(-1)
            return (per_frame * w).sum(1) / w.sum(1).clamp_min(1.0)
        return per_frame.mean(1)

    def forward_features(self, f: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """Logits from precomputed backbone features (frozen-backbone training)."""
        return self.classify(self.attend(f), keep)

    def forward(self, x: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        if x.ndim != 5 or x.shape[1] != self.n_frames:
            raise StamError(f"{self.name} expects B x {self.n_frames} x 3 x S x S input, got {tuple(x.shape)}")
        return self.forward_features(self.frame_features(x), keep)


# build()'s option defaults, against which variant() tells an option given on purpose from one left as is.
BUILD_DEFAULTS = {k: p.default for k, p in inspect.signature(SequenceModel.__init__).parameters.items()
                  if p.default is not inspect.Parameter.empty}


def build(name: str, n_frames: int, num_classes: int, **options) -> SequenceModel:
    """Build a model, an architecture (``cnn``, ``cnn_sa``, ``stam``) or a named variant of
    :data:`VARIANTS`, for windows of ``n_frames`` frames.

    Options (see the module docstring): width (channel multiplier, 1.0 = AlexNet),
    image_size (px, square input; 224), fusion, modules (10), combine, qk_reduction (8),
    residual_gain, sa_batchnorm, dropout (0.5), pool (fc6 input map side; default the
    last max-pool's map side), hidden (fc6/fc7 width; 0 = 4096 x width), attention_at (pool5 | conv5),
    window_hidden (512: the position-aware fusions' layer on the flattened window).
    """
    arch, options = variant(name, options)
    model = SequenceModel(arch, n_frames, num_classes, **options)
    model.variant = name
    return model


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (all trainable in these models)."""
    return sum(p.numel() for p in model.parameters())


def parameter_count(name: str, n_frames: int = 2, num_classes: int = 100, **options) -> int:
    """Parameter count of :func:`build` without allocating weights (meta device)."""
    with torch.device("meta"):
        return count_parameters(build(name, n_frames, num_classes, **options))


def paper_readings() -> list[dict]:
    """Parameter counts of several readings of the paper at its setting (full width, 224 px,
    100 classes, n = 2), to compare with its 57.4 M (baseline) and 68.8 M (STAM).

    Counts are computed from layer sizes; ``alexnet`` (57.41 M) is the baseline's.
    """
    c, hw, hidden, k, n, mods = 256, 36, 4096, 100, 2, 10
    alexnet = parameter_count("cnn", n, k)
    qkv_full = 3 * (c * c + c)  # one module with q, k, v all C -> C
    qkv_red8 = 2 * (c * (c // 8) + c // 8) + (c * c + c)
    rows = [
        ("cnn: AlexNet conv + fc6-fc8 (100 classes), parameter-free fusion", alexnet),
        ("stam default: + SA + 10 modules, q/k at C/8, gamma, mean-combined",
         parameter_count("stam", n, k)),
        ("stam: + SA + 10 modules with q, k, v all C -> C", parameter_count("stam", n, k, qk_reduction=1)),
        ("stam: + 10 modules C/8, concatenated and projected 2560 -> 256",
         parameter_count("stam", n, k, combine="concat")),
        ("stam, fc6 on the n frames' features concatenated (n*9216 -> 4096)",
         alexnet + n * c * hw * hidden - c * hw * hidden + mods * qkv_red8),
        ("stam, one FC on the flattened outputs of all 10 modules (no fc6/fc7)",
         alexnet - (c * hw * hidden + hidden) - (hidden * hidden + hidden) - (hidden * k + k)
         + mods * qkv_full + mods * n * c * hw * k + k),
        ("AlexNet + 10 full q,k,v modules + one FC flatten(n*h*w*C = 18432) -> 512",
         alexnet + mods * qkv_full + n * c * hw * 512 + 512),
        ("stam_paper: that, its 512 outputs joining the frames' mean fc7 into fc8 (4096 + 512 -> 100)",
         parameter_count("stam_paper", n, k)),
        ("AlexNet + 10 C/8 modules + FC on the pooled concatenation (2560 -> 4096)",
         alexnet + mods * qkv_red8 + mods * c * hidden + hidden),
    ]
    return [{"reading": r, "params": int(p), "params_m": round(p / 1e6, 2)} for r, p in rows]
