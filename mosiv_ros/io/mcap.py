"""MCAP chunk checksums, which the rosbags writer leaves out.

rosbags 0.11.9 writes every MCAP chunk with ``uncompressed_crc`` 0, which the MCAP format reads
as "no checksum", and has no option to write one: a bit flipped inside a chunk then reads as
data. ``add_chunk_crcs`` fills in each chunk's CRC32 (of its uncompressed records, as the
format defines it) once a file is written, in place: the field has a fixed width, so no offset
moves. rosbags' reader checks a non-zero CRC of every chunk it reads ("Chunk checksum
mismatch", a ``BagError`` through ``io.bag``), so bags written before, without checksums
(the committed sample bags), still read. ``chunk_crcs`` counts the chunks that carry one.

What it is for: ``io.bag.write_recording`` and ``mosiv info``. What it is not for: reading
messages (rosbags does).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import BinaryIO

from rosbags.rosbag2.storage_mcap import DECOMPRESSORS

MAGIC = b"\x89MCAP0\r\n"
_CHUNK, _FOOTER, _DATA_END = 0x06, 0x02, 0x0F
_CRC_OFFSET = 24
"""Bytes from a chunk record's content to its uncompressed_crc (after start, end and size)."""


def _chunk_offsets(file: BinaryIO) -> list[int]:
    """Where each chunk record's content starts (the data section, record by record).

    ValueError if the file is not MCAP or a record runs past its end.
    """
    if file.read(len(MAGIC)) != MAGIC:
        raise ValueError("not an MCAP file (no MCAP magic)")
    size = file.seek(0, 2)
    offsets, offset = [], len(MAGIC)
    while offset + 9 <= size:
        file.seek(offset)
        opcode, length = struct.unpack("<BQ", file.read(9))
        if opcode in (_DATA_END, _FOOTER):
            return offsets
        if offset + 9 + length > size:
            raise ValueError(f"a record at byte {offset} runs past the end of the file")
        if opcode == _CHUNK:
            offsets.append(offset + 9)
        offset += 9 + length
    raise ValueError("the data section has no end (truncated file?)")


def add_chunk_crcs(path: str | Path) -> int:
    """Write every chunk's CRC32 into the MCAP file at ``path``; return how many chunks it has."""
    with Path(path).open("r+b") as file:
        offsets = _chunk_offsets(file)
        for content in offsets:
            file.seek(content + _CRC_OFFSET - 8)
            (uncompressed_size,) = struct.unpack("<Q", file.read(8))
            file.seek(4, 1)  # the CRC itself
            (name_length,) = struct.unpack("<I", file.read(4))
            compression = file.read(name_length).decode()
            (records_length,) = struct.unpack("<Q", file.read(8))
            records = DECOMPRESSORS[compression](file.read(records_length), uncompressed_size)
            file.seek(content + _CRC_OFFSET)
            file.write(struct.pack("<I", zlib.crc32(records)))
    return len(offsets)


def chunk_crcs(path: str | Path) -> tuple[int, int]:
    """(chunks with a CRC, chunks) of the MCAP file at ``path``; ValueError if it is not one."""
    with Path(path).open("rb") as file:
        offsets = _chunk_offsets(file)
        with_crc = 0
        for content in offsets:
            file.seek(content + _CRC_OFFSET)
            with_crc += struct.unpack("<I", file.read(4))[0] != 0
    return with_crc, len(offsets)
