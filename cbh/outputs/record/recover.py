"""Recovery of a recording whose writer was killed (no summary, possibly a torn last record)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cbh.errors import RecordingError
from cbh.outputs.record.reader import MAGIC, PAIR_TOPIC
from cbh.outputs.record.writer import create_exclusive

__all__ = ["recover", "RecoveryReport"]


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` kept."""

    source: Path
    out: Path
    messages: int  # complete messages rewritten
    pairs: int  # complete pairs (their /pair/layers message survived)
    bytes_read: int  # bytes of the source up to the end of the last complete record
    bytes_total: int  # size of the source
    complete: bool  # the source already ended with a valid footer


def recover(path, out, *, overwrite: bool = False) -> RecoveryReport:
    """Rewrite every complete record of a (truncated) MCAP file into a valid MCAP ``out``.

    The source is read with mcap's non-seeking stream reader; reading stops at the first
    broken or incomplete record (the frame in flight when the writer was killed). Schemas,
    channels, metadata and messages before it are written, in order, to ``out`` with a fresh
    summary and footer. An existing ``out`` is refused unless ``overwrite`` (callers' own
    work files); ``cbh inspect --repair OTHER.mcap`` silently replaced another recording.
    """
    from mcap.records import Attachment, Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    src, dst = Path(path), Path(out)
    if not src.is_file():
        raise RecordingError(f"recording not found: {src}")
    if dst.exists() and dst.resolve() == src.resolve():
        raise RecordingError(f"--repair output must differ from the input: {dst}")
    total = src.stat().st_size
    with open(src, "rb") as fh:
        if fh.read(8) != MAGIC:
            raise RecordingError(f"{src}: not an MCAP file (bad magic bytes); nothing to recover")
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    topics: dict[int, str] = {}
    n_msgs = n_pairs = 0
    complete = False
    try:
        out_fh = create_exclusive(dst, overwrite)  # an existing file (another recording) is never replaced
    except FileExistsError:
        raise RecordingError(f"{dst} exists: --repair never replaces a file (give another path)") from None
    except OSError as exc:
        raise RecordingError(f"cannot create {dst}: {exc.strerror}") from None
    with open(src, "rb") as fh, out_fh:
        writer = Writer(out_fh, chunk_size=1, compression=CompressionType.ZSTD)
        writer.start(profile="", library="cbh recover")
        reader = StreamReader(fh, record_size_limit=total)
        good = 8
        try:
            for rec in reader.records:
                if isinstance(rec, Schema):
                    if rec.id not in schemas:
                        schemas[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in channels:
                        sid = schemas.get(rec.schema_id, 0)
                        channels[rec.id] = writer.register_channel(rec.topic, rec.message_encoding, sid, dict(rec.metadata))
                        topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    if rec.channel_id in channels:
                        writer.add_message(channels[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence)
                        n_msgs += 1
                        n_pairs += topics[rec.channel_id] == PAIR_TOPIC
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
                good = fh.tell()
            complete = True
        except Exception:  # the torn record at the end (EndOfFile, struct.error, zstd error, bad magic …)
            pass
        writer.finish()
    return RecoveryReport(src, dst, n_msgs, n_pairs, min(good, total), total, complete)
