"""Repair of an MCAP file left without its summary section (the writer was killed).

:func:`repair_mcap` rewrites such a file from its complete records (and the complete messages of
a chunk cut short) so that indexed readers open it; :func:`cobelrun.io.repair.repair_run` calls
it for a killed run's ``run.mcap``. Only the ``mcap`` package's public reader records and
``mcap.writer.Writer`` are used.
"""

from __future__ import annotations

import os
import struct
import tempfile
from collections.abc import Callable, Iterator
from io import BytesIO
from pathlib import Path
from typing import Any

__all__ = ["join_mcap", "repair_mcap"]

_MAGIC = b"\x89MCAP0\r\n"


def repair_mcap(path: str | os.PathLike[str]) -> bool:
    """Make an MCAP left unfinished (the writer was killed) readable by the indexed reader.

    The file is read record by record up to where it breaks off; every message of a complete
    chunk is kept, and so is every complete message at the start of a chunk that was being
    written (its compressed stream is decoded as far as it goes). Schemas, channels, metadata
    and attachments are kept. The result is written to a temporary file next to ``path`` and
    renamed over it, so ``path`` is never half-rewritten.

    Parameters
    ----------
    path : path-like
        The MCAP file.

    Returns
    -------
    bool
        True if the file was rewritten, False if it was complete already.

    Raises
    ------
    ValueError
        If the file does not start with the MCAP magic.
    """
    from mcap.reader import make_reader

    path = Path(path)
    with open(path, "rb") as f:
        if f.read(len(_MAGIC)) != _MAGIC:
            raise ValueError(f"{path} is not an MCAP file (bad magic)")
        f.seek(0, os.SEEK_END)
        if f.tell() >= 2 * len(_MAGIC):
            f.seek(-len(_MAGIC), os.SEEK_END)
            if f.read(len(_MAGIC)) == _MAGIC:
                f.seek(0)
                try:
                    make_reader(f).get_summary()
                    return False
                except Exception:  # any parse error means: rebuild
                    pass
    data = path.read_bytes()
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".repair", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as out:
            _rewrite(data, out)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return True


def _rewrite(data: bytes, out: Any) -> None:
    """Copy what is complete in ``data`` (an unfinished MCAP) into a new MCAP on ``out``."""
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    header: Header | None = None
    writer = Writer(out, compression=CompressionType.ZSTD)
    schema_ids: dict[int, int] = {0: 0}
    channel_ids: dict[int, int] = {}
    started = False

    def start() -> None:
        nonlocal started
        if not started:
            h = header or Header(profile="", library="")
            writer.start(profile=h.profile, library=h.library)
            started = True

    for rec in _complete_records(data):
        if isinstance(rec, Header):
            header = rec
            continue
        start()
        if isinstance(rec, Schema):
            if rec.id not in schema_ids:
                schema_ids[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel):
            if rec.id not in channel_ids and rec.schema_id in schema_ids:
                channel_ids[rec.id] = writer.register_channel(
                    rec.topic, rec.message_encoding, schema_ids[rec.schema_id], dict(rec.metadata)
                )
        elif isinstance(rec, Message):
            cid = channel_ids.get(rec.channel_id)
            if cid is not None:
                writer.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
        elif isinstance(rec, Metadata):
            writer.add_metadata(rec.name, dict(rec.metadata))
        elif isinstance(rec, Attachment):
            writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
    start()
    writer.finish()


def _complete_records(data: bytes) -> Iterator[Any]:
    """Records of an MCAP's data section, stopping where the file breaks off.

    Chunks are opened (CRC checked) and yield their schemas, channels and messages; a chunk
    cut off mid-way yields the complete records its partial zstd/lz4-free stream decodes to.
    """
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk

    readers = _record_readers()
    pos, end = len(_MAGIC), len(data)
    while pos + 9 <= end:
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        body_start = pos + 9
        if opcode == Opcode.CHUNK and body_start + length > end:
            yield from _partial_chunk(data, body_start)
            return
        if body_start + length > end:
            return  # the last record was cut off
        if opcode in (Opcode.DATA_END, Opcode.FOOTER):
            return
        body = ReadDataStream(BytesIO(data[body_start : body_start + length]))
        if opcode == Opcode.CHUNK:
            try:
                chunk = Chunk.read(body)
                records = breakup_chunk(chunk, validate_crc=True)
            except Exception:  # a damaged chunk ends what can be trusted
                return
            yield from records
        elif opcode in readers:
            try:
                yield readers[opcode](body, length)
            except Exception:
                return
        pos = body_start + length


def _record_readers() -> dict[int, Any]:
    from mcap.opcode import Opcode
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

    return {
        Opcode.HEADER: lambda s, n: Header.read(s),
        Opcode.SCHEMA: lambda s, n: Schema.read(s),
        Opcode.CHANNEL: lambda s, n: Channel.read(s),
        Opcode.MESSAGE: lambda s, n: Message.read(s, n),
        Opcode.METADATA: lambda s, n: Metadata.read(s),
        Opcode.ATTACHMENT: lambda s, n: Attachment.read(s),
    }


def _partial_chunk(data: bytes, body_start: int) -> Iterator[Any]:
    """Complete records at the start of a chunk whose writing was interrupted.

    The chunk header's lengths are placeholders then (the writer fills them in when the chunk
    ends), so the compressed stream runs to the end of the file; it is decoded as far as it
    goes and cut after the last complete record.
    """
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    p = body_start + 8 + 8 + 8 + 4  # start time, end time, uncompressed size, crc
    if p + 4 > len(data):
        return
    (clen,) = struct.unpack_from("<I", data, p)
    if p + 4 + clen + 8 > len(data):
        return
    compression = data[p + 4 : p + 4 + clen].decode("utf-8", "replace")
    payload = data[p + 4 + clen + 8 :]
    if compression == "zstd":
        import zstandard

        try:
            raw = zstandard.ZstdDecompressor().decompressobj().decompress(payload)
        except zstandard.ZstdError:
            return
    elif compression == "":
        raw = payload
    else:  # lz4 frames cannot be decoded partially here; drop the partial chunk
        return
    q, n = 0, len(raw)
    while q + 9 <= n:
        opcode = raw[q]
        (length,) = struct.unpack_from("<Q", raw, q + 1)
        if q + 9 + length > n:
            return
        body = ReadDataStream(BytesIO(raw[q + 9 : q + 9 + length]))
        try:
            if opcode == Opcode.MESSAGE:
                yield Message.read(body, length)
            elif opcode == Opcode.CHANNEL:
                yield Channel.read(body)
            elif opcode == Opcode.SCHEMA:
                yield Schema.read(body)
            else:
                return
        except Exception:
            return
        q += 9 + length


# ---------------------------------------------------------------------------- transitional


def join_mcap(
    first: str | os.PathLike[str],
    second: str | os.PathLike[str],
    out: str | os.PathLike[str],
    until_ns: int | Callable[[str, bytes], int | None],
) -> None:
    """Write one MCAP of ``first``'s messages logged before ``until_ns`` and ``second``'s
    from then on (a run resumed from a checkpoint: the stream up to the checkpoint, then the
    resumed process's). ``until_ns`` may be a function of a message's topic and data giving
    its own cut (None: the message is kept from both files), for timelines where each run
    has its own clock (:func:`cobelrun.io.mcap.per_run_cut`). Metadata and attachments are
    taken from ``first`` (``second`` repeats them); schemas and channels of both are kept.
    ``out`` may be ``second``: the result is written to a temporary file and renamed."""
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    out = Path(out)
    fd, tmp = tempfile.mkstemp(prefix=out.name + ".", suffix=".join", dir=out.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            writer: Any = None
            for source, index in ((Path(first), 0), (Path(second), 1)):
                schema_ids: dict[int, int] = {0: 0}
                channel_ids: dict[int, int] = {}
                topics: dict[int, str] = {}
                for rec in _complete_records(source.read_bytes()):
                    if isinstance(rec, Header):
                        if writer is None:
                            writer = Writer(fh, compression=CompressionType.ZSTD)
                            writer.start(profile=rec.profile, library=rec.library)
                        continue
                    if writer is None:
                        writer = Writer(fh, compression=CompressionType.ZSTD)
                        writer.start(profile="", library="")
                    if isinstance(rec, Schema) and rec.id not in schema_ids:
                        schema_ids[rec.id] = writer.register_schema(
                            rec.name, rec.encoding, rec.data
                        )
                    elif isinstance(rec, Channel):
                        topics.setdefault(rec.id, rec.topic)
                        if rec.id not in channel_ids and rec.schema_id in schema_ids:
                            channel_ids[rec.id] = writer.register_channel(
                                rec.topic, rec.message_encoding, schema_ids[rec.schema_id],
                                dict(rec.metadata),
                            )  # fmt: skip
                    elif isinstance(rec, Message):
                        cid = channel_ids.get(rec.channel_id)
                        if cid is None:
                            continue
                        cut = (until_ns(topics[rec.channel_id], rec.data) if callable(until_ns)
                               else until_ns)  # fmt: skip
                        if cut is not None and (rec.log_time >= cut) == (index == 0):
                            # the stopped process's past its checkpoint, or the resumed
                            # process's before it (the scene it logs again at the start)
                            continue
                        writer.add_message(cid, rec.log_time, rec.data, rec.publish_time,
                                           rec.sequence)  # fmt: skip
                    elif index == 0 and isinstance(rec, Metadata):
                        writer.add_metadata(rec.name, dict(rec.metadata))
                    elif index == 0 and isinstance(rec, Attachment):
                        writer.add_attachment(rec.create_time, rec.log_time, rec.name,
                                              rec.media_type, rec.data)  # fmt: skip
            if writer is None:
                raise ValueError(f"{first} and {second} hold no MCAP records")
            writer.finish()
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
