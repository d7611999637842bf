"""stam: the STAM tactile texture-recognition models (Cao et al., IROS 2020) in PyTorch.

Modules: ``backbone`` (AlexNet features and classifier head), ``models`` (the CNN
baseline, CNN + spatial attention and STAM), ``data`` (reader for ``gelsim generate``
datasets), ``config`` (presets into validated dataclasses), ``train``, ``evaluate``, ``experiment`` (the Tables I/II sweep),
``explain`` (Grad-CAM and temporal attention maps) and ``cli`` (the ``stam`` command).
Bad input raises :class:`stam.errors.StamError`, a GelsimError (one line, exit 2 on the CLI).
"""
from gelsim import __version__  # noqa: E402,F401  (one version for the distribution)
