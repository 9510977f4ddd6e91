"""ds3d: the dual-source approach to 3D human pose from a single image (Yasin et al., CVPR 2016)."""

__version__ = "0.1.0"

# Loaded on first use, so that `import ds3d` (the CLI, the client SDK) stays cheap.
_LAZY = {"Pipeline": "ds3d.pipeline", "Lifter": "ds3d.lifter", "predict": "ds3d.io.predictions"}
__all__ = ["Lifter", "Pipeline", "__version__", "predict"]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'ds3d' has no attribute {name!r}")
