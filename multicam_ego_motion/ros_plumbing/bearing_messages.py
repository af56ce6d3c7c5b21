"""A quarter's tracks at one frame as sensor_msgs/PointCloud2: one bearing ray (x, y, 1) per
track in the camera's optical frame (normalised, undistorted), with its track id and its std
in the same units (pixel std / focal length). The general arbiter fits the rig's metric motion
to them (arbiter_node/rig_motion_fit); a viewer shows them as rays at unit depth.

Written and read as CDR bytes (16 messages a frame, where rclpy's message objects cost twice
as much as rosbags' (wire_types), and rosbags' three times as much as putting the bytes together
here: the fields' part of this layout is always the same bytes; a cloud of another layout, or
whose padding is not zeros as rclpy's serializer leaves it, is read by rosbags). Float64 coordinates: what the general arbiter fits is what the quarter
computed, bit for bit (the sequential pipeline hands over the same arrays)."""
import struct

import numpy as np

from multicam_ego_motion.ros_plumbing.pose_messages import stamp_to_ns
from multicam_ego_motion.ros_plumbing.wire_types import TYPES, from_cdr, header, to_cdr

CLOUD_TYPE = 'sensor_msgs/msg/PointCloud2'
_Cloud, _Field = TYPES[CLOUD_TYPE], TYPES['sensor_msgs/msg/PointField']

POINT = np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('sigma', '<f8'), ('id', '<u4')])
FIELDS = [_Field(name=n, offset=POINT.fields[n][1], count=1,
                 datatype=_Field.UINT32 if n == 'id' else _Field.FLOAT64)
          for n in POINT.names]


# The bytes from the cloud's `fields` to `point_step` (little-endian CDR, starting 4-aligned:
# after height and width), the same for every message of this layout
_HEAD = struct.Struct('<iII')                 # stamp sec, nanosec, frame_id's length (with its NUL)
_DIMS = struct.Struct('<II')                  # height, width
_STEPS_DATA = struct.Struct('<III')           # point_step, row_step, data's length


def _fields_bytes() -> bytes:
    out = bytearray(struct.pack('<I', len(FIELDS)))
    for f in FIELDS:
        name = f.name.encode() + b'\0'
        out += struct.pack('<I', len(name)) + name
        out += b'\0' * (-len(out) % 4) + struct.pack('<IB', f.offset, f.datatype)
        out += b'\0' * (-len(out) % 4) + struct.pack('<I', f.count)
    return bytes(out) + b'\0'                # is_bigendian False (then 3 bytes' padding)


_FIELDS = _fields_bytes()


def _header_bytes(stamp_ns: int, frame_id: str) -> bytearray:
    name = frame_id.encode() + b'\0'
    out = bytearray(b'\0\x01\0\0')
    out += _HEAD.pack(int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000), len(name)) + name
    out += b'\0' * (-(len(out) - 4) % 4)
    return out


def bearings_to_cdr(stamp_ns: int, frame_id: str, ids, xy, sigma) -> bytes:
    """The serialized PointCloud2 a quarter publishes."""
    pts = np.zeros(len(ids), POINT)
    pts['x'], pts['y'], pts['z'] = xy[:, 0], xy[:, 1], 1.0
    pts['sigma'] = sigma
    pts['id'] = np.asarray(ids) & 0xFFFFFFFF     # a quarter numbers its tracks from 0
    out = _header_bytes(stamp_ns, frame_id)
    out += _DIMS.pack(1, len(pts)) + _FIELDS
    out += b'\0' * (-(len(out) - 4) % 4)
    out += _STEPS_DATA.pack(POINT.itemsize, POINT.itemsize * len(pts), pts.nbytes)
    out += pts.tobytes()
    out += b'\x01'                            # is_dense
    return bytes(out)


def _bearings_to_cdr_rosbags(stamp_ns: int, frame_id: str, ids, xy, sigma) -> bytes:
    """bearings_to_cdr by rosbags' serializer: the same bytes (test_bearing_messages)."""
    pts = np.zeros(len(ids), POINT)
    pts['x'], pts['y'], pts['z'] = xy[:, 0], xy[:, 1], 1.0
    pts['sigma'] = sigma
    pts['id'] = np.asarray(ids) & 0xFFFFFFFF
    msg = _Cloud(header=header(stamp_ns, frame_id), height=1, width=len(pts),
                 fields=FIELDS, is_bigendian=False, point_step=POINT.itemsize,
                 row_step=POINT.itemsize * len(pts), data=pts.view(np.uint8), is_dense=True)
    return to_cdr(msg, CLOUD_TYPE)


def _fast_read(data):
    """(stamp_ns, points) of a little-endian cloud of this layout and height 1 (is_dense and
    any padding after the data not read), else None."""
    buf = memoryview(data)
    if len(buf) < 16 or buf[0] != 0 or buf[1] != 1:
        return None
    sec, nanosec, n = _HEAD.unpack_from(buf, 4)
    pos = 16 + n
    pos += -(pos - 4) % 4
    if n == 0 or pos + 8 + len(_FIELDS) + 3 + 12 > len(buf):
        return None
    height, width = _DIMS.unpack_from(buf, pos)
    pos += 8
    if height != 1 or buf[pos:pos + len(_FIELDS)] != _FIELDS:
        return None
    pos += len(_FIELDS)
    pos += -(pos - 4) % 4
    point_step, row_step, size = _STEPS_DATA.unpack_from(buf, pos)
    pos += 12
    if point_step != POINT.itemsize or size != width * POINT.itemsize or not pos + size < len(buf) <= pos + size + 4:
        return None
    return sec * 1_000_000_000 + nanosec, np.frombuffer(buf[pos:pos + size], POINT)


def bearings_from_cdr(data):
    """(stamp_ns, ids, xy, sigma) of a serialized PointCloud2; ValueError naming the problem
    for bytes that are not one or a cloud of another layout."""
    fast = _fast_read(data)
    if fast is not None:
        stamp_ns, pts = fast
        return (stamp_ns, pts['id'].astype(np.int64), np.column_stack([pts['x'], pts['y']]),
                pts['sigma'].copy())
    msg = from_cdr(data, CLOUD_TYPE)
    names = [f.name for f in msg.fields]
    if names != list(POINT.names) or msg.point_step != POINT.itemsize or msg.is_bigendian:
        raise ValueError(f'bearings: expected fields {list(POINT.names)} ({POINT.itemsize} bytes a '
                         f'point, little-endian), got {names} ({msg.point_step} bytes)')
    n = msg.width * msg.height
    if len(msg.data) != n * POINT.itemsize:
        raise ValueError(f'bearings: {len(msg.data)} bytes for {n} points')
    pts = msg.data.view(POINT)
    return (stamp_to_ns(msg.header.stamp), pts['id'].astype(np.int64),
            np.column_stack([pts['x'], pts['y']]), pts['sigma'].copy())
