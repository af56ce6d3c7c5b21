"""A quarter's tracks at one frame as sensor_msgs/PointCloud2: one bearing ray (x, y, 1) per
track in the camera's optical frame (normalised, undistorted), with its track id and its std
in the same units (pixel std / focal length). The general arbiter fits the rig's metric motion
to them (arbiter_node/rig_motion_fit); a viewer shows them as rays at unit depth.

Written and read as CDR bytes (wire_types: 16 messages a frame, where rclpy's message objects
cost twice as much). Float64 coordinates: what the general arbiter fits is what the quarter
computed, bit for bit (the sequential pipeline hands over the same arrays)."""
import numpy as np

from multicam_ego_motion.ros_plumbing.pose_messages import stamp_to_ns
from multicam_ego_motion.ros_plumbing.wire_types import TYPES, from_cdr, header, to_cdr

CLOUD_TYPE = 'sensor_msgs/msg/PointCloud2'
_Cloud, _Field = TYPES[CLOUD_TYPE], TYPES['sensor_msgs/msg/PointField']

POINT = np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('sigma', '<f8'), ('id', '<u4')])
FIELDS = [_Field(name=n, offset=POINT.fields[n][1], count=1,
                 datatype=_Field.UINT32 if n == 'id' else _Field.FLOAT64)
          for n in POINT.names]


def bearings_to_cdr(stamp_ns: int, frame_id: str, ids, xy, sigma) -> bytes:
    """The serialized PointCloud2 a quarter publishes."""
    pts = np.zeros(len(ids), POINT)
    pts['x'], pts['y'], pts['z'] = xy[:, 0], xy[:, 1], 1.0
    pts['sigma'] = sigma
    pts['id'] = np.asarray(ids) & 0xFFFFFFFF     # a quarter numbers its tracks from 0
    msg = _Cloud(header=header(stamp_ns, frame_id), height=1, width=len(pts),
                 fields=FIELDS, is_bigendian=False, point_step=POINT.itemsize,
                 row_step=POINT.itemsize * len(pts), data=pts.view(np.uint8), is_dense=True)
    return to_cdr(msg, CLOUD_TYPE)


def bearings_from_cdr(data):
    """(stamp_ns, ids, xy, sigma) of a serialized PointCloud2; ValueError naming the problem
    for bytes that are not one or a cloud of another layout."""
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
