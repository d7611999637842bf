"""AlexNet in plain torch, with torchvision's layer specification.

torchvision cannot be installed next to the CPU torch here, so the layers are spelled
out: ``features`` = conv 64-11/4 p2, ReLU, max-pool 3/2, conv 192-5 p2, ReLU, max-pool,
conv 384-3 p1, ReLU, conv 256-3 p1, ReLU, conv 256-3 p1, ReLU, max-pool. STAM cuts the
network at that last max-pool (the paper's "output feature map from the last max-pooling
layer"). ``width`` multiplies every channel count and the fc hidden size, so that a
CPU-sized run keeps the architecture's shape. ``cut="conv5"`` stops before that max-pool
(the map conv5 gives, for models that attend there and pool afterwards).
"""
from __future__ import annotations

import torch
from torch import nn

# torchvision's AlexNet widths (conv1..conv5) and fc hidden size.
ALEXNET_CHANNELS = (64, 192, 384, 256, 256)
ALEXNET_HIDDEN = 4096
# torchvision pools the last feature map to 6x6 before fc6 (the map a 224 px input gives).
ALEXNET_POOL = 6
# Where the feature extractor stops: after the last max-pool (the paper's F) or before it.
CUTS = ("pool5", "conv5")


def scaled(c: int, width: float) -> int:
    """Channel count ``c`` times ``width``, at least 1."""
    return max(1, int(round(c * width)))


class AlexNetFeatures(nn.Module):
    """AlexNet's convolutional part; input ``B x 3 x S x S`` -> ``B x C x h x w``.

    At S = 224 px, (C, h, w) = (256 * width, 6, 6); at 160 px 4 x 4; at 128 px 3 x 3. With
    ``cut="conv5"`` the last max-pool is left out: 13 x 13 at 224 px, 7 x 7 at 128 px. (The pool
    has no weights, so one state dict serves both cuts.)
    """

    def __init__(self, width: float = 1.0, batchnorm: bool = False, cut: str = "pool5"):
        super().__init__()
        if cut not in CUTS:
            raise ValueError(f"cut {cut!r} unknown; use one of {', '.join(CUTS)}")
        c1, c2, c3, c4, c5 = (scaled(c, width) for c in ALEXNET_CHANNELS)
        self.out_channels = c5
        self.width = width
        self.batchnorm = batchnorm

        def conv(cin, cout, **kw):
            # BatchNorm only while pretraining from scratch; fold_batchnorm() merges it into the
            # convolution afterwards, so every model still gets torchvision's plain AlexNet layers.
            c = nn.Conv2d(cin, cout, **kw)
            return [c, nn.BatchNorm2d(cout), nn.ReLU(inplace=True)] if batchnorm else [c, nn.ReLU(inplace=True)]

        self.features = nn.Sequential(
            *conv(3, c1, kernel_size=11, stride=4, padding=2),
            nn.MaxPool2d(kernel_size=3, stride=2),
            *conv(c1, c2, kernel_size=5, padding=2),
            nn.MaxPool2d(kernel_size=3, stride=2),
            *conv(c2, c3, kernel_size=3, padding=1),
            *conv(c3, c4, kernel_size=3, padding=1),
            *conv(c4, c5, kernel_size=3, padding=1),
            *([nn.MaxPool2d(kernel_size=3, stride=2)] if cut == "pool5" else []),
        )
        self.cut = cut
        # He initialisation: with PyTorch's default (uniform, gain 1/sqrt(3)) five ReLU layers
        # without normalisation shrink the activations about 30-fold, and a model trained from
        # scratch (no ImageNet weights here) then barely moves off chance for several epochs.
        for m in self.features:
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_in", nonlinearity="relu")
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)


def fold_batchnorm(net: AlexNetFeatures) -> AlexNetFeatures:
    """The plain AlexNet (no BatchNorm) computing what ``net`` computes in eval mode.

    Each BatchNorm after a convolution is an affine map per output channel,
    ``y = (x - mean) / sqrt(var + eps) * gamma + beta``, so it folds into that
    convolution's weight and bias.
    """
    plain = AlexNetFeatures(net.width)
    if not net.batchnorm:
        plain.load_state_dict(net.state_dict())
        return plain
    mods = list(net.features)
    pairs = [(m, mods[i + 1]) for i, m in enumerate(mods) if isinstance(m, nn.Conv2d)]
    convs = [m for m in plain.features if isinstance(m, nn.Conv2d)]
    with torch.no_grad():
        for dst, (conv, bn) in zip(convs, pairs):
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            dst.weight.copy_(conv.weight * scale[:, None, None, None])
            dst.bias.copy_((conv.bias - bn.running_mean) * scale + bn.bias)
    return plain


def feature_size(image_size: int, cut: str = "pool5") -> int:
    """Side of the feature map for a square input of ``image_size`` px: the last max-pool's output
    (``cut="pool5"``) or conv5's, before it (``"conv5"``)."""
    s = (image_size + 2 * 2 - 11) // 4 + 1
    s = (s - 3) // 2 + 1
    s = (s - 3) // 2 + 1
    return s if cut == "conv5" else (s - 3) // 2 + 1


class AlexNetHead(nn.Module):
    """fc6-fc8 with dropout, on a ``B x C x h x w`` map -> ``B x num_classes`` logits.

    ``hidden`` is the fc6/fc7 width (default 4096 x width).

    Like torchvision, the map is adaptively average-pooled to ``pool x pool`` first
    (6 x 6 at the paper's setting, where it is a no-op for 224 px inputs).
    """

    def __init__(self, in_channels: int, num_classes: int, width: float = 1.0,
                 pool: int = ALEXNET_POOL, dropout: float = 0.5, hidden: int | None = None):
        super().__init__()
        hidden = hidden or scaled(ALEXNET_HIDDEN, width)
        self.pool = nn.AdaptiveAvgPool2d((pool, pool))
        self.classifier = nn.Sequential(
            nn.Dropout(dropout), nn.Linear(in_channels * pool * pool, hidden), nn.ReLU(inplace=True),
            nn.Dropout(dropout), nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
            nn.Linear(hidden, num_classes),
        )

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.classifier(torch.flatten(self.pool(f), 1))


class AlexNet(nn.Module):
    """Single-frame AlexNet classifier, used to pretrain the backbone (ImageNet's stand-in)."""

    def __init__(self, num_classes: int, width: float = 1.0, pool: int = ALEXNET_POOL, dropout: float = 0.5,
                 batchnorm: bool = False):
        super().__init__()
        self.backbone = AlexNetFeatures(width, batchnorm=batchnorm)
        self.head = AlexNetHead(self.backbone.out_channels, num_classes, width, pool, dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.backbone(x))
