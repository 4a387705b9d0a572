"""Error types of the ROS-free I/O layer.

One documented family: everything the bag, message, scene and output-file code raises on bad
input is a ``MosivIOError``. What it is for: telling a user which file, topic or field is wrong and how.
What it is not for: programming errors (wrong argument types in our own code stay TypeError etc.).

Every error type here survives pickling (the process runner may move them between processes).
"""

from __future__ import annotations

import os
import reprlib
from pathlib import Path

MAX_SHOWN_CHARS = 200
"""The most characters of a value that an error message shows (``shown``)."""
_SHOWN = reprlib.Repr()
_SHOWN.maxlevel = 3
_SHOWN.maxlist = _SHOWN.maxtuple = _SHOWN.maxdict = _SHOWN.maxset = 8
_SHOWN.maxstring = _SHOWN.maxother = _SHOWN.maxlong = MAX_SHOWN_CHARS


def shown(value: object) -> str:
    """``repr(value)`` for an error message: at most ``MAX_SHOWN_CHARS``, ``...`` where cut.

    Nested data is cut while it is written (reprlib), so even a value that YAML aliases made
    huge costs no time: messages embed what they were given through this, never whole.
    """
    text = _SHOWN.repr(value)
    return text if len(text) <= MAX_SHOWN_CHARS else text[: MAX_SHOWN_CHARS - 3] + "..."


def not_utf8(error: UnicodeDecodeError) -> str:
    """The problem of a text file that is not UTF-8, for a message that names the file."""
    return f"not UTF-8 text (byte 0x{error.object[error.start]:02x} at offset {error.start})"


class MosivIOError(Exception):
    """Base class of every error raised by ``mosiv_ros.io`` on bad input data."""


class BagError(MosivIOError):
    """A rosbag2 recording cannot be read or written as mosiv_ros expects.

    Attributes:
        path: the bag directory (or the path given for it).
        topic: the topic at fault, or None when the problem is not tied to one topic.
        problem: what is wrong, in words.
    """

    def __init__(self, path: str | os.PathLike[str], topic: str | None, problem: str) -> None:
        self.path = Path(path)
        self.topic = topic
        self.problem = problem
        super().__init__(str(self))

    def __str__(self) -> str:
        where = f"{self.path}: topic {self.topic}" if self.topic else str(self.path)
        return f"{where}: {self.problem}"

    def __reduce__(self) -> tuple[type[BagError], tuple[Path, str | None, str]]:
        return (type(self), (self.path, self.topic, self.problem))


class MessageError(MosivIOError, ValueError):
    """A message (or an array meant for one) has the wrong encoding, size or field layout.

    The text names the message field and says what was expected and what was found.
    """


class SceneError(MosivIOError, ValueError):
    """A scene declaration is invalid.

    Attributes:
        field: where in the declaration, e.g. ``objects[1].family`` (empty for the whole text).
        problem: what is wrong, in words.
        source: where the declaration came from (file, bag, ``<string>``), or None.
    """

    def __init__(self, field: str, problem: str, source: str | None = None) -> None:
        self.field = field
        self.problem = problem
        self.source = source
        super().__init__(str(self))

    def __str__(self) -> str:
        text = f"{self.field}: {self.problem}" if self.field else self.problem
        return f"{self.source}: {text}" if self.source else text

    def __reduce__(self) -> tuple[type[SceneError], tuple[str, str, str | None]]:
        return (type(self), (self.field, self.problem, self.source))


class OutputError(MosivIOError):
    """An output location cannot take the files: not a directory, not creatable, not writable.

    Attributes:
        path: the output path at fault.
        problem: what is wrong, in words.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(str(self))

    def __str__(self) -> str:
        return f"output {self.path}: {self.problem}"

    def __reduce__(self) -> tuple[type[OutputError], tuple[Path, str]]:
        return (type(self), (self.path, self.problem))
