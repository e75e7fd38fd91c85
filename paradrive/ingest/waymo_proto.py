"""The Waymo Open Dataset ``Frame`` messages the builder reads, with the official field numbers.

Declared from ``waymo_open_dataset/dataset.proto`` (package ``waymo.open_dataset``, proto2).
Only the fields ingest needs; everything else in a record (labels, map features, segmentation,
...) is skipped by the decoder. Repeated numeric fields follow proto2: unpacked unless the
.proto says ``[packed = true]`` (MatrixFloat.data, MatrixInt32.data).
"""

from __future__ import annotations

from paradrive.ingest.protowire import Field, MessageType, decode

# CameraName.Name
CAMERA_NAMES = {0: "UNKNOWN", 1: "FRONT", 2: "FRONT_LEFT", 3: "FRONT_RIGHT", 4: "SIDE_LEFT",
                5: "SIDE_RIGHT"}
CAMERA_IDS = {v: k for k, v in CAMERA_NAMES.items()}
# LaserName.Name
LASER_NAMES = {0: "UNKNOWN", 1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}
LASER_IDS = {v: k for k, v in LASER_NAMES.items()}

MatrixShape = MessageType("MatrixShape", {
    1: Field("dims", "int32", repeated=True),
})
MatrixFloat = MessageType("MatrixFloat", {
    1: Field("data", "float", repeated=True, packed=True),
    2: Field("shape", MatrixShape),
})
MatrixInt32 = MessageType("MatrixInt32", {
    1: Field("data", "int32", repeated=True, packed=True),
    2: Field("shape", MatrixShape),
})
# 4x4 row-major transform.
Transform = MessageType("Transform", {
    1: Field("transform", "double", repeated=True),
})
Velocity = MessageType("Velocity", {
    1: Field("v_x", "float"),
    2: Field("v_y", "float"),
    3: Field("v_z", "float"),
    4: Field("w_x", "double"),
    5: Field("w_y", "double"),
    6: Field("w_z", "double"),
})
CameraCalibration = MessageType("CameraCalibration", {
    1: Field("name", "enum"),
    # [f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3]
    2: Field("intrinsic", "double", repeated=True),
    # camera frame (x forward, y left, z up) -> vehicle frame
    3: Field("extrinsic", Transform),
    4: Field("width", "int32"),
    5: Field("height", "int32"),
    6: Field("rolling_shutter_direction", "enum"),
})
LaserCalibration = MessageType("LaserCalibration", {
    1: Field("name", "enum"),
    2: Field("beam_inclinations", "double", repeated=True),
    3: Field("beam_inclination_min", "double"),
    4: Field("beam_inclination_max", "double"),
    5: Field("extrinsic", Transform),
})
ContextStats = MessageType("Context.Stats", {
    2: Field("time_of_day", "string"),
    3: Field("location", "string"),
    4: Field("weather", "string"),
})
Context = MessageType("Context", {
    1: Field("name", "string"),
    2: Field("camera_calibrations", CameraCalibration, repeated=True),
    3: Field("laser_calibrations", LaserCalibration, repeated=True),
    4: Field("stats", ContextStats),
})
RangeImage = MessageType("RangeImage", {
    # zlib-compressed serialized MatrixFloat [H, W, 4]: range, intensity, elongation, no-label-zone
    2: Field("range_image_compressed", "bytes"),
    3: Field("camera_projection_compressed", "bytes"),
    # zlib-compressed serialized MatrixFloat [H, W, 6]: roll, pitch, yaw, x, y, z (vehicle->global)
    4: Field("range_image_pose_compressed", "bytes"),
    1: Field("range_image", MatrixFloat),  # deprecated
})
CameraImage = MessageType("CameraImage", {
    1: Field("name", "enum"),
    2: Field("image", "bytes"),           # JPEG
    3: Field("pose", Transform),          # vehicle -> global at pose_timestamp
    4: Field("velocity", Velocity),
    5: Field("pose_timestamp", "double"),
    6: Field("shutter", "double"),
    7: Field("camera_trigger_time", "double"),
    8: Field("camera_readout_done_time", "double"),
})
Laser = MessageType("Laser", {
    1: Field("name", "enum"),
    2: Field("ri_return1", RangeImage),
    3: Field("ri_return2", RangeImage),
})
# label.proto: an upright box in the vehicle frame of its frame
LabelBox = MessageType("Label.Box", {
    1: Field("center_x", "double"),
    2: Field("center_y", "double"),
    3: Field("center_z", "double"),
    4: Field("width", "double"),
    5: Field("length", "double"),
    6: Field("height", "double"),
    7: Field("heading", "double"),        # rad, +x rotated to the box front, in [-pi, pi)
})
LabelMetadata = MessageType("Label.Metadata", {
    1: Field("speed_x", "double"),
    2: Field("speed_y", "double"),
    3: Field("accel_x", "double"),
    4: Field("accel_y", "double"),
})
# Label.Type: 0 unknown, 1 vehicle, 2 pedestrian, 3 sign, 4 cyclist
Label = MessageType("Label", {
    1: Field("box", LabelBox),
    2: Field("metadata", LabelMetadata),
    3: Field("type", "enum"),
    4: Field("id", "string"),
})
Frame = MessageType("Frame", {
    1: Field("context", Context),
    2: Field("timestamp_micros", "int64"),
    3: Field("pose", Transform),          # vehicle -> global
    4: Field("images", CameraImage, repeated=True),
    5: Field("lasers", Laser, repeated=True),
    6: Field("laser_labels", Label, repeated=True),
})


def decode_frame(data):
    """Decode one TFRecord payload as a Frame."""
    return decode(Frame, data)
