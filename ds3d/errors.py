"""Typed errors of the library. The service maps each to an HTTP status."""


class Ds3dError(Exception):
    """Base class of every error ds3d raises on purpose."""


class InvalidPose(Ds3dError, ValueError):
    """A 2D or 3D pose has the wrong shape, too few joints, or non-finite values."""


class InvalidImage(Ds3dError, ValueError):
    """An image is empty, corrupt, not an image, or too large to decode."""


class ImageTooLarge(InvalidImage):
    """An image's header claims more pixels than the limit it is decoded under."""


class InvalidBox(Ds3dError, ValueError):
    """A person box is not four finite numbers, has reversed corners or no area, or lies outside
    its image."""


class DataFormatError(Ds3dError, ValueError):
    """A dataset or model file is missing, malformed or not what its reader expects."""
