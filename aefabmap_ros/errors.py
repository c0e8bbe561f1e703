"""The one error hierarchy of the package.

Every error a user can cause (bad file, bad parameter, bad message) is an
``AefabmapError``; CLIs print its message as ``ERROR: ...`` and exit 1, nodes
log it and drop the input. Messages name the offending value.
"""


class AefabmapError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(AefabmapError, ValueError):
    """A configuration value is out of range or inconsistent."""


class ModelError(AefabmapError):
    """A model directory is missing, corrupt, of another version or vocabulary."""


class VocabularyMismatchError(ModelError):
    """Data (a map, a message, a file) belongs to a different vocabulary."""


class ImageError(AefabmapError, ValueError):
    """An image cannot be decoded: unsupported encoding, wrong size, corrupt data."""


class ImageTooLargeError(ImageError):
    """An image has more pixels than allowed: refused before it is decoded."""


class BagError(AefabmapError):
    """A rosbag2 bag is missing, corrupt, empty, or lacks the requested topic."""


class DataError(AefabmapError, ValueError):
    """Input arrays have the wrong shape, dtype or range."""
