"""MCAP recordings of a cell: one channel per Zenoh key with the raw msgpack payloads, and,
given a :class:`service.foxglove.FoxgloveMirror`, Foxglove channels (JSON with JSON schemas)
beside them so the file opens in Foxglove.

Times are integer nanoseconds. ``log_time`` is when the message was seen (the recorder's clock
for live recordings, the publication schedule for generated ones); replay follows log-time
order. Reading stops with :class:`RecordingError` at the first damaged record, after yielding
every message before it, so the frames before the damage can still be used.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel, Footer, Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from posefuse.estimator.core.errors import PosefuseError
from posefuse.service.foxglove import schema_bytes

RAW_ENCODING = "msgpack"
PROFILE = "posefuse"


class RecordingError(PosefuseError):
    """A recording that is missing, not MCAP, or damaged."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


@dataclass(frozen=True)
class RecordedMessage:
    log_time_ns: int
    key: str
    payload: bytes


class Recorder:
    """Writes raw key/payload messages to an MCAP file (a context manager).

    With a ``mirror``, each raw message is followed by its Foxglove messages, on channels of
    their own (message encoding ``json``, schema encoding ``jsonschema``), at the same log time.

    A full disk: the recorder keeps ``reserve_bytes`` of disk allocated beside the file. When a
    write fails (``OSError``, e.g. no space left), the file is cut back to the end of the last
    complete chunk, :meth:`write` raises :class:`RecordingFull` naming how many messages are in
    the file, and :meth:`close` frees the reserve first, so the summary and the footer still
    fit: the recording stays a valid MCAP of everything before the failure.
    """

    def __init__(
        self,
        path: str | Path,
        metadata: dict[str, str] | None = None,
        mirror=None,
        reserve_bytes: int = 1 << 20,
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._reserve = self.path.with_name(f".{self.path.name}.reserve")
        try:
            with open(self._reserve, "wb") as f:
                os.posix_fallocate(f.fileno(), 0, reserve_bytes)
        except (OSError, AttributeError):
            self._reserve.unlink(missing_ok=True)
        self.written = 0  # raw messages handed to the writer
        self.in_file = 0  # raw messages in complete chunks on disk
        self.footer_written = False
        self._closed = False
        self._failed: OSError | None = None
        self._file = self.path.open("wb")
        # small chunks: a damaged file loses little (each chunk is read whole or not at all)
        self._writer = Writer(self._file, chunk_size=64 * 1024, compression=CompressionType.ZSTD)
        self._writer.start(PROFILE, "posefuse")
        self._channels: dict[str, int] = {}
        self._json_channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._mirror = mirror
        self._sequence = 0
        if metadata:
            self._writer.add_metadata("posefuse", {str(k): str(v) for k, v in metadata.items()})

    def write(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if self._failed is not None:
            raise RecordingFull(self.path, self.in_file, self._failed)
        good_end, good_count = self._file.tell(), self.in_file
        try:
            self._write(key, payload, log_time_ns)
        except OSError as exc:
            self._failed = exc
            self.in_file = good_count
            try:  # drop the partial chunk: the file ends with complete records again
                self._file.truncate(good_end)
                self._file.seek(good_end)
            except OSError:
                pass
            raise RecordingFull(self.path, self.in_file, exc) from None
        if self._file.tell() != good_end:  # a chunk went to disk, this message's included
            self.in_file = self.written

    def _write(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if key not in self._channels:
            self._channels[key] = self._writer.register_channel(key, RAW_ENCODING, 0)
        self._sequence += 1
        self._writer.add_message(
            self._channels[key],
            int(log_time_ns),
            bytes(payload),
            int(log_time_ns),
            self._sequence,
        )
        self.written += 1
        if self._mirror is not None:
            for m in self._mirror.convert(key, payload, log_time_ns):
                self.write_json(m.topic, m.schema, m.data(), log_time_ns)

    def write_json(self, topic: str, schema_name: str, data: bytes, log_time_ns: int) -> None:
        """A JSON message of a schema of :data:`service.foxglove.SCHEMAS` on ``topic``."""
        if schema_name not in self._schemas:
            self._schemas[schema_name] = self._writer.register_schema(
                schema_name, "jsonschema", schema_bytes(schema_name)
            )
        if topic not in self._json_channels:
            self._json_channels[topic] = self._writer.register_channel(
                topic, "json", self._schemas[schema_name]
            )
        self._sequence += 1
        self._writer.add_message(
            self._json_channels[topic], int(log_time_ns), data, int(log_time_ns), self._sequence
        )

    def close(self) -> bool:
        """Finish the file (summary and footer); True when the footer was written."""
        if self._closed:
            return self.footer_written
        self._closed = True
        self._reserve.unlink(missing_ok=True)
        try:
            self._writer.finish()
            self._file.flush()
            self.footer_written = True
            if self._failed is None:
                self.in_file = self.written
        except OSError:
            self.footer_written = False
        finally:
            try:
                self._file.close()
            except OSError:
                self.footer_written = False
        return self.footer_written

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RecordingFull(RecordingError):
    """Writing failed (a full disk, a quota): no more messages go to this file."""

    def __init__(self, path: Path, in_file: int, cause: OSError):
        self.in_file = in_file
        self.cause = cause
        super().__init__(path, f"{cause.strerror or cause}; {in_file} messages are in the file")


def read_messages(path: str | Path) -> Iterator[RecordedMessage]:
    """Raw messages in file order (the recorder writes them in log-time order).

    Reads the file as a stream, so a truncated or corrupt file yields every message before
    the damage and then raises RecordingError naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(path, "file not found")
    channels: dict[int, Channel] = {}
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        raise RecordingError(
                            path, f"message on unknown channel {record.channel_id}"
                        )
                    if channel.message_encoding == RAW_ENCODING:
                        yield RecordedMessage(record.log_time, channel.topic, record.data)
                elif isinstance(record, Footer):
                    return
        except RecordingError:
            raise
        except Exception as exc:  # the stream reader raises many unrelated types on damage
            raise RecordingError(
                path, f"damaged after the last good message ({type(exc).__name__})"
            ) from None
    raise RecordingError(path, "truncated: no footer")
