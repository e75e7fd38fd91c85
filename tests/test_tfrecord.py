"""TFRecord container (masked CRC32C framing) and the protobuf wire codec, without TensorFlow."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from paradrive.ingest import protowire as pw
from paradrive.ingest import tfrecord as tfr
from paradrive.ingest import waymo_proto as wp


def _crc32c_bitwise(data: bytes) -> int:
    """The CRC-32C definition, one bit at a time (reflected polynomial 0x82F63B78)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc32c_matches_published_check_values():
    assert tfr.crc32c(b"123456789") == 0xE3069283  # the CRC-32C check value
    assert tfr.crc32c(bytes(32)) == 0x8A9136AA     # RFC 3720 B.4, 32 zero bytes
    assert tfr.crc32c(bytes([0xFF] * 32)) == 0x62A8AB43
    assert tfr.crc32c(bytes(range(32))) == 0x46DD794E


@pytest.mark.parametrize("n", [0, 1, 3, 4095, 4099, 20_011])
def test_crc32c_equals_the_bitwise_definition(n):
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert tfr.crc32c(data) == _crc32c_bitwise(data)


def test_crc32c_takes_any_bytes_like_object():
    data = b"waymo segment record"
    expected = _crc32c_bitwise(data)
    assert tfr.crc32c(bytearray(data)) == expected
    assert tfr.crc32c(memoryview(data)) == expected
    assert tfr.crc32c(memoryview(b"xx" + data)[2:]) == expected


def test_crc32c_runs_in_the_compiled_library():
    import google_crc32c

    # the pure-Python fallback of google-crc32c would take minutes per segment
    assert google_crc32c.implementation == "c"


def test_masked_crc_follows_tfrecord_definition():
    crc = tfr.crc32c(b"abc")
    assert tfr.masked_crc32c(b"abc") == (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def test_record_layout_is_length_crc_data_crc():
    rec = tfr.encode_record(b"hello")
    length, length_crc = struct.unpack_from("<QI", rec)
    assert length == 5 and length_crc == tfr.masked_crc32c(rec[:8])
    assert rec[12:17] == b"hello"
    assert struct.unpack_from("<I", rec, 17)[0] == tfr.masked_crc32c(b"hello")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.binary(max_size=5000), max_size=6))
def test_records_round_trip(tmp_path_factory, records):
    path = tmp_path_factory.mktemp("rt") / "x.tfrecord"
    assert tfr.write_records(path, records) == len(records)
    assert tfr.read_records(path) == records


def _three_records(tmp_path):
    path = tmp_path / "seg.tfrecord"
    tfr.write_records(path, [b"a" * 100, b"b" * 200, b"c" * 300])
    return path


def test_corrupt_data_is_a_crc_mismatch_naming_the_record(tmp_path):
    path = _three_records(tmp_path)
    raw = bytearray(path.read_bytes())
    raw[(8 + 4 + 100 + 4) + 12 + 50] ^= 0x01  # one bit inside record 1's data
    path.write_bytes(bytes(raw))
    with pytest.raises(tfr.RecordError, match=r"record 1 at byte 116: data CRC mismatch"):
        tfr.read_records(path)
    assert len(tfr.read_records(path, verify=False)) == 3


def test_corrupt_length_is_a_header_crc_mismatch(tmp_path):
    path = _three_records(tmp_path)
    raw = bytearray(path.read_bytes())
    raw[0] ^= 0x02
    path.write_bytes(bytes(raw))
    with pytest.raises(tfr.RecordError, match=r"record 0 at byte 0: length CRC mismatch"):
        tfr.read_records(path)


def test_truncated_file_names_the_cut_record(tmp_path):
    path = _three_records(tmp_path)
    raw = path.read_bytes()
    path.write_bytes(raw[:-10])
    with pytest.raises(tfr.RecordError, match=r"record 2 .*truncated record"):
        tfr.read_records(path)
    path.write_bytes(raw[: len(raw) - (300 + 16) + 5])
    with pytest.raises(tfr.RecordError, match=r"record 2 .*truncated header"):
        tfr.read_records(path)


def test_writing_is_atomic(tmp_path):
    path = tmp_path / "seg.tfrecord"

    def boom():
        yield b"ok"
        raise RuntimeError("disk gone")

    with pytest.raises(RuntimeError):
        tfr.write_records(path, boom())
    assert not path.exists() and list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- wire format

def test_wire_codec_round_trips_a_frame():
    frame = {
        "context": {"name": "seg", "camera_calibrations": [
            {"name": 1, "intrinsic": [2000.5, 2001.25, 960.0, 640.0, -0.3, 0.1, 1e-3, -2e-3, 0.0],
             "extrinsic": {"transform": list(np.arange(16) / 7.0)}, "width": 1920,
             "height": 1280}]},
        "timestamp_micros": 1_557_962_554_000_000,
        "pose": {"transform": [float(x) for x in np.eye(4).reshape(-1)]},
        "images": [{"name": 1, "image": b"\xff\xd8jpeg", "pose_timestamp": 1.5}],
    }
    out = wp.decode_frame(pw.encode(wp.Frame, frame))
    cal = out.context.camera_calibrations[0]
    assert out.context.name == "seg" and out.timestamp_micros == 1_557_962_554_000_000
    assert cal.intrinsic == frame["context"]["camera_calibrations"][0]["intrinsic"]
    assert cal.extrinsic.transform == list(np.arange(16) / 7.0)
    assert (cal.width, cal.height) == (1920, 1280)
    assert bytes(out.images[0].image) == b"\xff\xd8jpeg"
    assert out.lasers == [] and out.images[0].pose is None  # defaults for absent fields


def test_negative_and_zigzag_varints_round_trip():
    t = pw.MessageType("T", {1: pw.Field("a", "int32"), 2: pw.Field("b", "sint64"),
                             3: pw.Field("c", "int64", repeated=True, packed=True),
                             4: pw.Field("d", "bool")})
    msg = pw.decode(t, pw.encode(t, {"a": -5, "b": -(2**40), "c": [-1, 0, 2**62], "d": True}))
    assert (msg.a, msg.b, msg.c, msg.d) == (-5, -(2**40), [-1, 0, 2**62], True)


def test_truncated_message_is_a_wire_error():
    data = pw.encode(wp.Transform, {"transform": [1.0] * 16})
    with pytest.raises(pw.WireError):
        pw.decode(wp.Transform, data[:-3])


def _official_classes():
    """The same messages built with the protobuf runtime, to check against the official codec."""
    descriptor_pb2 = pytest.importorskip("google.protobuf.descriptor_pb2")
    from google.protobuf import descriptor_pool, message_factory

    fdp = descriptor_pb2.FileDescriptorProto(name="wod_check.proto", package="wodcheck",
                                             syntax="proto2")
    F = descriptor_pb2.FieldDescriptorProto
    shape = fdp.message_type.add(name="MatrixShape")
    shape.field.add(name="dims", number=1, type=F.TYPE_INT32, label=F.LABEL_REPEATED)
    mf = fdp.message_type.add(name="MatrixFloat")
    f = mf.field.add(name="data", number=1, type=F.TYPE_FLOAT, label=F.LABEL_REPEATED)
    f.options.packed = True
    mf.field.add(name="shape", number=2, type=F.TYPE_MESSAGE, label=F.LABEL_OPTIONAL,
                 type_name=".wodcheck.MatrixShape")
    tr = fdp.message_type.add(name="Transform")
    tr.field.add(name="transform", number=1, type=F.TYPE_DOUBLE, label=F.LABEL_REPEATED)
    cc = fdp.message_type.add(name="CameraCalibration")
    cc.field.add(name="name", number=1, type=F.TYPE_INT32, label=F.LABEL_OPTIONAL)
    cc.field.add(name="intrinsic", number=2, type=F.TYPE_DOUBLE, label=F.LABEL_REPEATED)
    cc.field.add(name="extrinsic", number=3, type=F.TYPE_MESSAGE, label=F.LABEL_OPTIONAL,
                 type_name=".wodcheck.Transform")
    cc.field.add(name="width", number=4, type=F.TYPE_INT32, label=F.LABEL_OPTIONAL)
    cc.field.add(name="height", number=5, type=F.TYPE_INT32, label=F.LABEL_OPTIONAL)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    get = message_factory.GetMessageClass
    return {n: get(pool.FindMessageTypeByName(f"wodcheck.{n}"))
            for n in ("MatrixFloat", "Transform", "CameraCalibration")}


def test_codec_agrees_with_the_protobuf_runtime():
    cls = _official_classes()
    official = cls["CameraCalibration"](name=3, intrinsic=[1.5, -2.25, 3e-9], width=832,
                                        height=480)
    official.extrinsic.transform.extend([0.5] * 16)
    ours = pw.decode(wp.CameraCalibration, official.SerializeToString())
    assert (ours.name, ours.intrinsic, ours.width, ours.height) == (3, [1.5, -2.25, 3e-9], 832, 480)
    assert ours.extrinsic.transform == [0.5] * 16
    # and the other way: our bytes parse with the runtime, byte for byte the same encoding
    data = pw.encode(wp.CameraCalibration, ours)
    parsed = cls["CameraCalibration"]()
    parsed.ParseFromString(data)
    assert parsed == official and data == official.SerializeToString()
    mf = pw.encode(wp.MatrixFloat, {"data": [1.0, -2.5, 3.25], "shape": {"dims": [1, 3]}})
    parsed_mf = cls["MatrixFloat"]()
    parsed_mf.ParseFromString(mf)
    assert list(parsed_mf.data) == [1.0, -2.5, 3.25] and list(parsed_mf.shape.dims) == [1, 3]
    assert mf == parsed_mf.SerializeToString()  # packed floats, as the .proto declares
