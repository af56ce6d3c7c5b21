"""A quarter's tracks at one frame as sensor_msgs/PointCloud2: one bearing ray (x, y, 1) per
track in the camera's optical frame (normalised, undistorted), with its track id and its std
in the same units (pixel std / focal length). The general arbiter fits the rig's metric motion
to them (arbiter_node/rig_motion_fit); a viewer shows them as rays at unit depth.

Float64 coordinates: what the general arbiter fits is what the quarter computed, bit for bit
(the sequential pipeline hands over the same arrays)."""
import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from multicam_ego_motion.ros_plumbing.pose_messages import ns_to_stamp, stamp_to_ns

POINT = np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('sigma', '<f8'), ('id', '<u4')])
FIELDS = [PointField(name=n, offset=POINT.fields[n][1], count=1,
                     datatype=PointField.UINT32 if n == 'id' else PointField.FLOAT64)
          for n in POINT.names]


def bearings_to_msg(stamp_ns: int, frame_id: str, ids, xy, sigma) -> PointCloud2:
    pts = np.zeros(len(ids), POINT)
    pts['x'], pts['y'], pts['z'] = xy[:, 0], xy[:, 1], 1.0
    pts['sigma'] = sigma
    pts['id'] = np.asarray(ids) & 0xFFFFFFFF     # a quarter numbers its tracks from 0
    msg = PointCloud2(height=1, width=len(pts), fields=FIELDS, is_bigendian=False,
                      point_step=POINT.itemsize, row_step=POINT.itemsize * len(pts), is_dense=True)
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.data = pts.tobytes()
    return msg


def msg_to_bearings(msg: PointCloud2):
    """(stamp_ns, ids, xy, sigma); ValueError naming the problem for a cloud of another layout."""
    names = [f.name for f in msg.fields]
    if names != list(POINT.names) or msg.point_step != POINT.itemsize or msg.is_bigendian:
        raise ValueError(f'bearings: expected fields {list(POINT.names)} ({POINT.itemsize} bytes a '
                         f'point, little-endian), got {names} ({msg.point_step} bytes)')
    n = msg.width * msg.height
    if len(msg.data) != n * POINT.itemsize:
        raise ValueError(f'bearings: {len(msg.data)} bytes for {n} points')
    pts = np.frombuffer(bytes(msg.data), POINT)
    xy = np.column_stack([pts['x'], pts['y']])
    return stamp_to_ns(msg.header.stamp), pts['id'].astype(np.int64), xy, pts['sigma'].copy()
