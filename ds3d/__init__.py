"""ds3d: the dual-source approach to 3D human pose from a single image (Yasin et al., CVPR 2016)."""

__version__ = "0.1.0"
