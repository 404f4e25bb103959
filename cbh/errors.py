"""One small exception hierarchy. The CLI turns any :class:`CbhError` into a one-line
message and exit code 2."""


class CbhError(Exception):
    """Base class of every error cbh raises on bad input or a failed resource."""


class ConfigError(CbhError, ValueError):
    """A station, scene or pipeline configuration is malformed (message names the key)."""


class CalibrationError(CbhError, ValueError):
    """A camera calibration file or inline intrinsics cannot be used."""


class ImageError(CbhError, ValueError):
    """An image is missing, unreadable, or does not match its calibration."""


class InputError(CbhError, ValueError):
    """Tabular or command-line input is malformed (message names row and column)."""


class SourceError(CbhError, RuntimeError):
    """A frame source (camera stream, file, directory) failed."""


class RecordingError(CbhError, RuntimeError):
    """A recording (MCAP, RRD, export) cannot be read or written."""


class ShapeError(CbhError, ValueError):
    """An array argument has the wrong shape; the message gives expected vs actual."""


def check_shape(name: str, arr, shape: tuple) -> None:
    """Raise :class:`ShapeError` unless ``arr.shape`` matches ``shape``.

    ``shape`` entries are ints or ``None`` (any size), e.g. ``(None, 2)``.
    """
    actual = tuple(arr.shape)
    if len(actual) != len(shape) or any(s is not None and s != a for s, a in zip(shape, actual)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"{name}: expected shape {want}, got {actual}")
