"""TFRecord files: the container Waymo segments ship in, read and written without TensorFlow.

A record is::

    uint64 length            (little endian)
    uint32 masked_crc32c(length bytes)
    bytes  data[length]
    uint32 masked_crc32c(data)

CRC32C is the Castagnoli CRC (reflected polynomial 0x82F63B78, init and final xor 0xFFFFFFFF);
the mask is ``((crc >> 15) | (crc << 17)) + 0xA282EAD8`` modulo 2**32.

The CRC is computed by ``google-crc32c`` (a dependency: the C implementation behind Google's
storage clients, hardware CRC32C instructions where the CPU has them).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from collections.abc import Iterable, Iterator

import google_crc32c

from paradrive.io import atomic_path

MASK_DELTA = 0xA282EAD8
_HEADER = struct.Struct("<QI")
_FOOTER = struct.Struct("<I")


class RecordError(ValueError):
    """A TFRecord file is corrupt: names the record index and its byte offset."""

    def __init__(self, message: str, *, index: int, offset: int):
        self.index = index
        self.offset = offset
        self.reason = message
        super().__init__(f"record {index} at byte {offset}: {message}")


# --------------------------------------------------------------------------- CRC32C

def crc32c(data: bytes | bytearray | memoryview) -> int:
    """CRC32C (Castagnoli) of a bytes-like object."""
    return int(google_crc32c.value(data if isinstance(data, bytes) else bytes(data)))


def masked_crc32c(data: bytes | bytearray | memoryview) -> int:
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + MASK_DELTA) & 0xFFFFFFFF


# --------------------------------------------------------------------------- reading

def iter_records(path: str | os.PathLike, *, verify: bool = True) -> Iterator[bytes]:
    """Yield the data of each record in ``path``, one record in memory at a time.

    Raises RecordError naming the record on a truncated record or a CRC mismatch
    (``verify=False`` skips the CRC checks but still checks lengths).
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        offset, index = 0, 0
        while offset < size:
            header = f.read(_HEADER.size)
            if len(header) < _HEADER.size:
                raise RecordError(f"truncated header ({len(header)} of {_HEADER.size} bytes)",
                                  index=index, offset=offset)
            length, length_crc = _HEADER.unpack(header)
            if verify and masked_crc32c(header[:8]) != length_crc:
                raise RecordError("length CRC mismatch (corrupt header)", index=index,
                                  offset=offset)
            if offset + _HEADER.size + length + _FOOTER.size > size:
                present = max(0, size - offset - _HEADER.size - _FOOTER.size)
                raise RecordError(f"truncated record: {length} data bytes declared, "
                                  f"at most {present} present", index=index, offset=offset)
            data = f.read(length)
            footer = f.read(_FOOTER.size)
            if len(data) < length or len(footer) < _FOOTER.size:
                raise RecordError("truncated record (file shrank while reading)", index=index,
                                  offset=offset)
            if verify and masked_crc32c(data) != _FOOTER.unpack(footer)[0]:
                raise RecordError("data CRC mismatch (corrupt record)", index=index,
                                  offset=offset)
            yield data
            offset += _HEADER.size + length + _FOOTER.size
            index += 1


def read_records(path: str | os.PathLike, *, verify: bool = True) -> list[bytes]:
    """All records of ``path`` as bytes (copies; for small files and tests)."""
    return [bytes(r) for r in iter_records(path, verify=verify)]


# --------------------------------------------------------------------------- writing

def encode_record(data: bytes) -> bytes:
    header = struct.pack("<Q", len(data))
    return (header + struct.pack("<I", masked_crc32c(header)) + bytes(data)
            + struct.pack("<I", masked_crc32c(data)))


def write_records(path: str | os.PathLike, records: Iterable[bytes]) -> int:
    """Write ``records`` to ``path`` atomically; returns the number of records."""
    count = 0
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            for data in records:
                f.write(encode_record(data))
                count += 1
    return count
