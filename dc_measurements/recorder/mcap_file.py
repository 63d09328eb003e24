"""One incident's messages written as an MCAP file of the ros2 profile, atomically.

Schemas are ``ros2msg`` definitions (dc_measurements.recorder.definitions), messages stay the CDR the
subscriptions took: nothing is decoded or encoded again. Each message has its receive time
(``log_time``) and the publisher's source time (``publish_time``). The file is written beside its
final name and renamed into place: an upload never sees half of it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dc_measurements.recorder.ring import Entry

COMPRESSIONS = ("zstd", "lz4", "none")


@dataclass(frozen=True)
class Channel:
    topic: str
    typename: str
    offered_qos_profiles: str = ""


@dataclass(frozen=True)
class Written:
    size: int
    # Types no definition was found for: their channels have no schema (the messages are in the file).
    without_definition: list[str]


def write_mcap(
    path: str,
    channels: list[Channel | None],
    entries: list[Entry],
    compression: str,
    definition: Callable[[str], str | None],
) -> Written:
    """Write ``entries`` (topic index into ``channels``; a topic not subscribed is None and has none) to
    ``path``, each type's schema from ``definition(type name)``."""
    from mcap.writer import CompressionType, Writer

    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as stream:
            writer = Writer(stream, compression=CompressionType[compression.upper()])
            writer.start(profile="ros2", library="dc")
            channel_ids: dict[int, int] = {}
            schema_ids: dict[str, int] = {}
            without: list[str] = []
            for index, channel in enumerate(channels):
                if channel is None:
                    continue
                if channel.typename not in schema_ids:
                    text = definition(channel.typename)
                    if text is None:
                        without.append(channel.typename)
                    schema_ids[channel.typename] = (
                        0 if text is None else writer.register_schema(channel.typename, "ros2msg", text.encode())
                    )
                schema_id = schema_ids[channel.typename]
                channel_ids[index] = writer.register_channel(
                    channel.topic, "cdr", schema_id, {"offered_qos_profiles": channel.offered_qos_profiles}
                )
            sequence = [0] * len(channels)
            for receive_ns, publish_ns, topic, data in sorted(entries, key=lambda e: e[0]):
                sequence[topic] += 1
                writer.add_message(channel_ids[topic], receive_ns, data, publish_ns or receive_ns, sequence[topic])
            writer.finish()
            size = stream.tell()
        os.replace(temporary, target)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return Written(size, without)
