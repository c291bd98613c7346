"""One small error hierarchy; each class also inherits from the built-in it refines (as soundfile does)."""
from __future__ import annotations


class AdhocArrayError(Exception):
    """Base class of every error the engine raises on purpose."""


class InputFileError(AdhocArrayError, ValueError):
    """A recording is missing, unreadable, corrupt or unusable."""


class ConfigError(AdhocArrayError, ValueError):
    """An option or configuration file is invalid."""


class StreamError(AdhocArrayError, RuntimeError):
    """The stream cannot go on (for example, no device delivers audio)."""


class AudioDeviceError(AdhocArrayError, RuntimeError):
    """A sound card or its system library is missing or fails."""
