"""gelsim: a GelSight tactile simulator and synthetic dataset generator.

Pipeline, each stage a plain module with typed inputs and outputs::

    fabrics (heightfield, mm) -> contact (MuJoCo pose and forces per frame)
      -> gel (imprint height map, marker positions) -> optics (uint8 RGB frame)
      -> dataset (videos, labels, manifest)
"""
__version__ = "0.1.0"

from .errors import GelsimError  # noqa: E402,F401
