"""`McapRecorder`: ROS 2 messages into an MCAP file that Foxglove opens and ``ros2 bag play`` replays.
Messages are stored as ROS 2 does (profile ``ros2``): CDR bytes under a ``ros2msg`` schema, the message definition.

The schema of a type is its ``.msg`` file followed by the files of every type it uses, each after a line of 80
``=`` and ``MSG: package/Type`` (the concatenated definition rosbag2 writes, read by Foxglove and mcap-ros2-support).
The ``.msg`` files come with the ROS message wheels, under ``<prefix>/share/<package>/msg/``.
"""

from __future__ import annotations

import os
import re
import stat
import sys
import sysconfig
from pathlib import Path
from typing import Any, BinaryIO

__all__ = ["McapRecorder", "RecordingError", "message_definition"]

_SEPARATOR = "=" * 80
#: The primitive types of ROS 2 interface definitions (array and bound suffixes stripped).
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
               "int64", "uint64", "string", "wstring"}
_FIELD_TYPE = re.compile(r"^([A-Za-z0-9_/]+)")


class RecordingError(RuntimeError):
    """The recording cannot be written (a message definition not found, the file not writable)."""


def _share_prefixes() -> list[Path]:
    """Where the ROS packages' ``share/`` folders may be: the ament prefixes, this environment's data prefix."""
    prefixes = [Path(entry) for entry in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if entry]
    prefixes += [Path(sysconfig.get_path("data")), Path(sys.prefix)]
    return list(dict.fromkeys(prefixes))


def _msg_file(package: str, name: str) -> str:
    for prefix in _share_prefixes():
        path = prefix / "share" / package / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text()
    raise RecordingError(f"no definition of {package}/msg/{name} under {[str(p) for p in _share_prefixes()]}")


def _dependencies(package: str, text: str) -> list[tuple[str, str]]:
    """The (package, Type) of every non-primitive field type of a ``.msg`` text, in order of appearance."""
    found = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        match = _FIELD_TYPE.match(line)  # the type, without an array or bound suffix ("float64[36]", "string<=8")
        base = match.group(1) if match else ""
        if not base or base in _PRIMITIVES:
            continue
        if "/" in base:
            parts = base.split("/")
            found.append((parts[0], parts[-1]))
        else:  # a type of the same package
            found.append((package, base))
    return found


def message_definition(type_name: str) -> str:
    """The concatenated ``ros2msg`` definition of ``type_name`` (``package/msg/Type``).

    :raises RecordingError: a ``.msg`` file that is not installed."""
    package, _, name = type_name.split("/")
    text = _msg_file(package, name)
    parts, seen, todo = [text], {(package, name)}, list(_dependencies(package, text))
    while todo:
        dependency = todo.pop(0)
        if dependency in seen:
            continue
        seen.add(dependency)
        body = _msg_file(*dependency)
        parts.append(f"{_SEPARATOR}\nMSG: {dependency[0]}/{dependency[1]}\n{body}")
        todo.extend(_dependencies(dependency[0], body))
    return "\n".join(parts)


class McapRecorder:
    """Write ROS 2 messages (objects or serialized CDR bytes) to ``path``, one channel per topic.

    :param path: the ``.mcap`` file (replaced). Close it with :meth:`close` (or use it as a context manager): the
        file's summary is written then.
    :raises RecordingError: ``path`` is not a regular file or a new file in a writable directory (a FIFO, a device,
        a link into /proc, a directory), or cannot be opened.
    """

    def __init__(self, path: str | Path) -> None:
        from mcap.writer import Writer
        from rclpy.serialization import serialize_message

        from socnav.io import OutputPathError, check_output_file

        self.path = Path(path)
        self._serialize = serialize_message
        try:
            check_output_file(self.path, what="recording", force=True)
        except OutputPathError as exc:
            raise RecordingError(str(exc)) from None
        self._stream: BinaryIO = self._open(self.path)
        self._writer = Writer(self._stream)
        self._writer.start(profile="ros2", library="socnav")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self.messages = 0

    @staticmethod
    def _open(path: Path) -> BinaryIO:
        """``path`` opened for writing, truncated, if it is a regular file (or new) when opened: non-blocking, so
        that a FIFO put there since it was checked fails at once instead of waiting for a reader."""
        try:
            descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK, 0o666)
        except OSError as exc:
            raise RecordingError(f"{path}: cannot write the recording ({exc.strerror or exc})") from None
        if not stat.S_ISREG(os.fstat(descriptor).st_mode):
            os.close(descriptor)
            raise RecordingError(f"{path} is not a regular file; give a new file for the recording")
        os.set_blocking(descriptor, True)
        return os.fdopen(descriptor, "wb")

    def channel(self, topic: str, type_name: str) -> int:
        """The channel of ``topic`` carrying ``type_name`` (``package/msg/Type``), registered on first use."""
        if topic not in self._channels:
            if type_name not in self._schemas:
                self._schemas[type_name] = self._writer.register_schema(
                    name=type_name, encoding="ros2msg", data=message_definition(type_name).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="cdr",
                                                                  schema_id=self._schemas[type_name])
        return self._channels[topic]

    def write(self, topic: str, message: Any, time_ns: int, type_name: str | None = None) -> None:
        """Record ``message`` on ``topic`` at ``time_ns``: a message object (its type read from it), or CDR bytes
        with their ``type_name``."""
        if isinstance(message, (bytes, bytearray)):
            if type_name is None:
                raise ValueError("serialized messages need their type_name")
            data = bytes(message)
        else:
            module = type(message).__module__.split(".")[0]
            type_name = type_name or f"{module}/msg/{type(message).__name__}"
            data = self._serialize(message)
        self._sequence += 1
        self._writer.add_message(channel_id=self.channel(topic, type_name), log_time=int(time_ns), data=data,
                                 publish_time=int(time_ns), sequence=self._sequence)
        self.messages += 1

    def close(self) -> None:
        """Finish the file (its summary and index); idempotent."""
        if not self._stream.closed:
            self._writer.finish()
            self._stream.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
