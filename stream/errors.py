"""One small error hierarchy; each class also inherits from the built-in it refines (as soundfile does)."""
from __future__ import annotations

import shlex
from pathlib import Path

# containers that phones, cameras and browsers record in, which libsndfile does not read
NOT_READ_CONTAINERS = (".m4a", ".aac", ".mp4", ".3gp", ".amr", ".wma", ".webm", ".mkv", ".mov")


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


def why_unreadable(path, err: BaseException) -> str:
    """soundfile's reason why ``path`` cannot be opened, and for a container libsndfile does not read (a phone's
    M4A, AMR or 3GP) what to do about it; for the parentheses of "... is not a readable audio file (...)"."""
    suffix = Path(path).suffix.lower()
    if suffix in NOT_READ_CONTAINERS:
        name, flac = shlex.quote(Path(path).name), shlex.quote(Path(path).stem + ".flac")
        return (f"{str(err).rstrip('.')}; libsndfile reads WAV, FLAC, OGG, MP3, AIFF and more, but not "
                f"{suffix[1:].upper()}: convert it first, e.g. ffmpeg -i {name} {flac}")
    return str(err)
