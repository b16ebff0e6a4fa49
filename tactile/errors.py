"""The package's exception tree: one base, one branch per boundary.

Everything a user can cause (a bad file, a bad port, a model whose contract we cannot honour)
raises a subclass of :class:`TactileError` with a one-line message; CLIs print that line and exit
non-zero. Bugs are left to raise whatever Python raises.
"""


class TactileError(Exception):
    """Base of every error this package raises on purpose."""


class ConfigError(TactileError, ValueError):
    """A setting is unknown, of the wrong type, or out of range."""


class DeviceError(TactileError):
    """The pen or its port: cannot open, vanished, or speaks something we do not understand."""


class FrameError(DeviceError):
    """A wire frame cannot be built (raised by the encoder, never by the stream decoder)."""


class RecordingError(TactileError):
    """A recording file or dataset folder is missing, malformed or inconsistent."""


class OutputError(TactileError):
    """A command's output cannot be written (stdout on a full disk, an I/O error)."""


class ModelContractError(TactileError):
    """An ONNX model's inputs, outputs or metadata do not honour the runtime's contract."""
