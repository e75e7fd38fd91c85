"""A minimal protobuf wire-format decoder and encoder, driven by declared message types.

Only what reading and writing logs needs: scalar fields (varint, zigzag, fixed 32/64, float,
double, bool, enum), strings, bytes, nested messages, repeated fields packed or not (a reader
accepts both, as protobuf parsers must). Unknown fields are skipped. Decoded messages are
``Message`` objects with attribute access and proto defaults for absent fields; ``bytes`` fields
are zero-copy ``memoryview`` slices of the input.

    Transform = MessageType("Transform", {1: Field("transform", "double", repeated=True)})
    t = decode(Transform, data); t.transform  # -> list of floats
    data = encode(Transform, {"transform": [1.0, 0.0, ...]})
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

VARINT, I64, LEN, I32 = 0, 1, 2, 5

_VARINT_KINDS = {"int32", "int64", "uint32", "uint64", "sint32", "sint64", "bool", "enum"}
_I64_KINDS = {"double": "<d", "fixed64": "<Q", "sfixed64": "<q"}
_I32_KINDS = {"float": "<f", "fixed32": "<I", "sfixed32": "<i"}
_NUMERIC = _VARINT_KINDS | set(_I64_KINDS) | set(_I32_KINDS)


class WireError(ValueError):
    """The bytes are not a valid encoding of the declared message."""


@dataclass(frozen=True)
class Field:
    name: str
    kind: str | MessageType  # a scalar kind name or a nested MessageType
    repeated: bool = False
    packed: bool = False       # how the encoder writes a repeated numeric field

    @property
    def is_message(self) -> bool:
        return isinstance(self.kind, MessageType)

    @property
    def message(self) -> MessageType:
        """The nested message type (a message field)."""
        assert isinstance(self.kind, MessageType), self.name
        return self.kind

    @property
    def scalar(self) -> str:
        """The scalar kind name (any other field)."""
        assert isinstance(self.kind, str), self.name
        return self.kind


@dataclass
class MessageType:
    name: str
    fields: dict[int, Field] = field(default_factory=dict)

    def __post_init__(self):
        self.by_name = {f.name: (num, f) for num, f in self.fields.items()}
        for f in self.fields.values():
            if not f.is_message and f.kind not in _NUMERIC | {"string", "bytes"}:
                raise ValueError(f"{self.name}.{f.name}: unknown kind {f.kind!r}")

    def __hash__(self):
        return id(self)


class Message:
    """A decoded message: attributes for declared fields (defaults when absent)."""

    __slots__ = ("_type", "_values")

    def __init__(self, mtype: MessageType, values: dict):
        object.__setattr__(self, "_type", mtype)
        object.__setattr__(self, "_values", values)

    def __getattr__(self, name):
        values = object.__getattribute__(self, "_values")
        if name in values:
            return values[name]
        mtype = object.__getattribute__(self, "_type")
        if name not in mtype.by_name:
            raise AttributeError(f"{mtype.name} has no field {name!r}")
        return _default(mtype.by_name[name][1])

    def has(self, name: str) -> bool:
        return name in self._values

    def to_dict(self) -> dict:
        return dict(self._values)

    def __repr__(self):
        return f"{self._type.name}({', '.join(sorted(self._values))})"


def _default(f: Field):
    if f.repeated:
        return []
    if f.is_message:
        return None
    if f.kind == "string":
        return ""
    if f.kind == "bytes":
        return b""
    if f.kind in ("double", "float"):
        return 0.0
    if f.kind == "bool":
        return False
    return 0


# --------------------------------------------------------------------------- decoding

def read_varint(buf, pos: int) -> tuple[int, int]:
    result = 0
    shift = 0
    n = len(buf)
    while True:
        if pos >= n:
            raise WireError("truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift >= 70:
            raise WireError("varint longer than 10 bytes")


def iter_fields(buf):
    """Yield (field_number, wire_type, value) for every field in ``buf``.

    value: int for VARINT, memoryview for LEN, I64 and I32 (the raw little-endian bytes).
    """
    buf = memoryview(buf).cast("B") if not isinstance(buf, memoryview) else buf
    pos, n = 0, len(buf)
    while pos < n:
        key, pos = read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise WireError("field number 0")
        if wire == VARINT:
            value, pos = read_varint(buf, pos)
        elif wire == LEN:
            length, pos = read_varint(buf, pos)
            if pos + length > n:
                raise WireError(f"field {number}: length {length} runs past the end")
            value = buf[pos:pos + length]
            pos += length
        elif wire == I64:
            if pos + 8 > n:
                raise WireError(f"field {number}: truncated fixed64")
            value = buf[pos:pos + 8]
            pos += 8
        elif wire == I32:
            if pos + 4 > n:
                raise WireError(f"field {number}: truncated fixed32")
            value = buf[pos:pos + 4]
            pos += 4
        else:
            raise WireError(f"field {number}: unsupported wire type {wire}")
        yield number, wire, value


def _signed(value: int, bits: int) -> int:
    value &= (1 << 64) - 1
    if value >= 1 << 63:
        value -= 1 << 64
    if bits == 32:
        value = (value + (1 << 31)) % (1 << 32) - (1 << 31)
    return value


def _convert_varint(kind: str, value: int):
    if kind in ("int64", "enum"):
        return _signed(value, 64)
    if kind == "int32":
        return _signed(value, 32)
    if kind == "uint32":
        return value & 0xFFFFFFFF
    if kind == "uint64":
        return value & ((1 << 64) - 1)
    if kind in ("sint32", "sint64"):
        return (value >> 1) ^ -(value & 1)
    if kind == "bool":
        return bool(value)
    raise WireError(f"kind {kind} is not a varint")


def _unpack_packed(kind: str, data: memoryview) -> list:
    if kind in _I64_KINDS or kind in _I32_KINDS:
        fmt = _I64_KINDS.get(kind) or _I32_KINDS[kind]
        size = struct.calcsize(fmt)
        if len(data) % size:
            raise WireError(f"packed {kind} field of {len(data)} bytes")
        return np.frombuffer(data, dtype=np.dtype(fmt)).tolist()
    out, pos = [], 0
    while pos < len(data):
        v, pos = read_varint(data, pos)
        out.append(_convert_varint(kind, v))
    return out


def _expect(wire: int, wanted: int, what: str) -> None:
    if wire != wanted:
        raise WireError(f"wire type {wire}, expected {what}")


def _decode_value(f: Field, wire: int, raw):
    """One non-packed value of field ``f`` from its raw wire payload."""
    if f.is_message:
        _expect(wire, LEN, "a message")
        return decode(f.message, raw)
    if f.kind in ("string", "bytes"):
        _expect(wire, LEN, "length-delimited")
        return bytes(raw).decode("utf-8") if f.kind == "string" else raw
    if f.kind in _VARINT_KINDS:
        _expect(wire, VARINT, "varint")
        return _convert_varint(f.scalar, raw)
    if f.kind in _I64_KINDS:
        _expect(wire, I64, "fixed64")
        return struct.unpack(_I64_KINDS[f.scalar], raw)[0]
    _expect(wire, I32, "fixed32")
    return struct.unpack(_I32_KINDS[f.scalar], raw)[0]


def decode(mtype: MessageType, buf) -> Message:
    """Decode ``buf`` as ``mtype``; WireError when the bytes do not fit the declaration."""
    values: dict = {}
    fields = mtype.fields
    for number, wire, raw in iter_fields(buf):
        f = fields.get(number)
        if f is None:
            continue
        try:
            if wire == LEN and f.repeated and not f.is_message and f.kind not in ("string", "bytes"):
                values.setdefault(f.name, []).extend(_unpack_packed(f.scalar, raw))
                continue
            value = _decode_value(f, wire, raw)
        except WireError as exc:
            raise WireError(f"{mtype.name}.{f.name} (field {number}): {exc}") from None
        except UnicodeDecodeError as exc:
            raise WireError(f"{mtype.name}.{f.name} (field {number}): not UTF-8") from exc
        if f.repeated:
            values.setdefault(f.name, []).append(value)
        else:
            values[f.name] = value  # last one wins, as in protobuf
    return Message(mtype, values)


# --------------------------------------------------------------------------- encoding

def encode_varint(value: int) -> bytes:
    if value < 0:
        value += 1 << 64
    out = bytearray()
    while True:
        b = value & 0x7F
        value >>= 7
        if value:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return encode_varint((number << 3) | wire)


def _varint_value(kind: str, value) -> int:
    if kind in ("sint32", "sint64"):
        v = int(value)
        return (v << 1) ^ (v >> 63)
    if kind == "bool":
        return 1 if value else 0
    return int(value)


def _scalar_payload(kind: str, value) -> bytes:
    if kind in _VARINT_KINDS:
        return encode_varint(_varint_value(kind, value))
    if kind in _I64_KINDS:
        return struct.pack(_I64_KINDS[kind], value)
    return struct.pack(_I32_KINDS[kind], value)


def _wire_of(kind: str) -> int:
    if kind in _VARINT_KINDS:
        return VARINT
    if kind in _I64_KINDS:
        return I64
    if kind in _I32_KINDS:
        return I32
    return LEN


def encode(mtype: MessageType, values: dict | Message) -> bytes:
    """Encode a dict (field name -> value; nested messages as dicts, bytes or Message) as ``mtype``."""
    if isinstance(values, Message):
        values = values.to_dict()
    unknown = set(values) - set(mtype.by_name)
    if unknown:
        raise ValueError(f"{mtype.name} has no field(s) {sorted(unknown)}")
    out = bytearray()
    for number in sorted(mtype.fields):
        f = mtype.fields[number]
        if f.name not in values or values[f.name] is None:
            continue
        value = values[f.name]
        items = list(value) if f.repeated else [value]
        if f.is_message:
            for item in items:
                payload = item if isinstance(item, (bytes, bytearray, memoryview)) else encode(f.message, item)
                out += _key(number, LEN) + encode_varint(len(payload)) + bytes(payload)
        elif f.kind in ("string", "bytes"):
            for item in items:
                payload = item.encode("utf-8") if isinstance(item, str) else bytes(item)
                out += _key(number, LEN) + encode_varint(len(payload)) + payload
        elif f.repeated and f.packed:
            if not items:
                continue
            if f.kind in _I64_KINDS or f.kind in _I32_KINDS:
                fmt = _I64_KINDS.get(f.scalar) or _I32_KINDS[f.scalar]
                payload = np.asarray(items, dtype=np.dtype(fmt)).tobytes()
            else:
                payload = b"".join(encode_varint(_varint_value(f.scalar, v)) for v in items)
            out += _key(number, LEN) + encode_varint(len(payload)) + payload
        else:
            key = _key(number, _wire_of(f.scalar))
            for item in items:
                out += key + _scalar_payload(f.scalar, item)
    return bytes(out)
