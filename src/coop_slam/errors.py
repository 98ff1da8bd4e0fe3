"""Exception hierarchy: every module raises its own subclass of :class:`CoopSlamError`.

Messages are written for the user: they name what is wrong and, where possible, what to do about it.
"""


class CoopSlamError(Exception):
    """Base class of all errors coop_slam raises on purpose."""


class ConfigError(CoopSlamError):
    """A configuration value or file is invalid."""


class GeometryError(CoopSlamError):
    """A pose or transform is not a valid rigid-body transform (NaN, not orthonormal, ...)."""
