"""The bag layout every camera-rig bag of this project has, for synthetic and imported data:

  /<cam>/image_raw    sensor_msgs/Image (mono8), frame <cam>_optical, one per frame; for a
                      camera whose rig transport is `compressed`, sensor_msgs/CompressedImage
                      on /<cam>/image_raw/compressed instead (JPEG or PNG, image_transport's
                      format string "mono8; jpeg compressed mono8")
  /<cam>/camera_info  sensor_msgs/CameraInfo (plumb_bob), with every image
  /tf_static          tf2_msgs/TFMessage: base_link -> each <cam>_optical, once at the start
  /ground_truth/odom  nav_msgs/Odometry odom -> base_link, pose in odom, twist in base_link
  /wheel/odom         nav_msgs/Odometry (optional), same frames
  /imu/data           sensor_msgs/Imu (optional, generated bags with an IMU rate): angular
                      velocity and specific force in imu_link, no orientation (covariance -1);
                      base_link -> imu_link in /tf_static

All images of a frame carry the same header stamp (free-running cameras: each image its own
capture instant, the frame being whichever images were written together); the log time of
every message is its header stamp.
"""
import cv2
import numpy as np

from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer
from multicam_ego_motion.geometry.se3 import R_to_quat_xyzw
from multicam_ego_motion.ros_plumbing.wire_types import TYPES, header, to_cdr

# Header stamps of generated and imported bags start here (2024-01-01T00:00:00Z), so that
# runs are reproducible byte for byte and never mistaken for wall-clock time.
STAMP_EPOCH_NS = 1_704_067_200 * 1_000_000_000

# Serialized with rosbags (wire_types), not rclpy: rclpy leaves CDR padding bytes
# uninitialized, so the same message would not give the same bytes twice (and a generated bag
# must). The CDR is the same standard encoding a subscriber receives; rosbags also knows
# tf2_msgs, so /tf_static is written whether or not tf2_msgs is built here.


def vector3(v):
    return TYPES['geometry_msgs/msg/Vector3'](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def quaternion(R):
    q = R_to_quat_xyzw(R)
    return TYPES['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                              w=float(q[3]))


IMAGE_CODECS = ('jpeg', 'png')


class RigBagWriter:
    def __init__(self, path, rig, intrinsics: dict, compression: str = 'zstd',
                 image_codec: str = 'jpeg', jpeg_quality: int = 90):
        """`intrinsics`: camera name -> CameraIntrinsics; `image_codec` (IMAGE_CODECS) and
        `jpeg_quality` for the cameras whose transport is `compressed`."""
        self.rig = rig
        self.intrinsics = intrinsics
        if image_codec not in IMAGE_CODECS:
            raise ValueError(f'image codec {image_codec!r} (one of {IMAGE_CODECS})')
        self.image_codec, self.jpeg_quality = image_codec, int(jpeg_quality)
        self.bag = Rosbag2Writer(path, compression=compression)
        for cam in rig.cameras:
            self.bag.add_topic(cam.input_topic, cam.input_type)
            self.bag.add_topic(cam.camera_info_topic, 'sensor_msgs/msg/CameraInfo')

    def _write(self, topic, typename, msg, time_ns):
        self.bag.write_serialized(topic, typename, to_cdr(msg, typename),
                                  time_ns)

    def write_static_transforms(self, time_ns: int, footprint: bool = False):
        """base_link -> each camera's optical frame and the rig's IMU's frame; with
        `footprint` also base_link -> base_footprint on the rig's floor (REP-120), from which
        a rig built from /tf_static takes its floor_z."""
        frames = [(cam.frame_id, cam.translation, cam.rotation) for cam in self.rig.cameras]
        if footprint and self.rig.floor_z is not None:
            frames.append(('base_footprint', (0.0, 0.0, self.rig.floor_z), np.eye(3)))
        if self.rig.imu is not None:
            frames.append((self.rig.imu.frame_id, self.rig.imu.translation, self.rig.imu.rotation))
        transforms = [TYPES['geometry_msgs/msg/TransformStamped'](
            header=header(time_ns, self.rig.base_frame), child_frame_id=child,
            transform=TYPES['geometry_msgs/msg/Transform'](
                translation=vector3(t), rotation=quaternion(R)))
            for child, t, R in frames]
        self._write('/tf_static', 'tf2_msgs/msg/TFMessage',
                    TYPES['tf2_msgs/msg/TFMessage'](transforms=transforms), time_ns)

    def write_images(self, time_ns: int, images: dict):
        """One frame: `images` maps camera name -> mono8 array; all share the stamp. Cameras
        not in `images` have no image at this stamp (free-running or slower cameras)."""
        for cam in self.rig.cameras:
            if cam.name not in images:
                continue
            img = np.ascontiguousarray(images[cam.name], dtype=np.uint8)
            if cam.transport == 'compressed':
                msg = self.compressed(img, header(time_ns, cam.frame_id))
            else:
                msg = TYPES['sensor_msgs/msg/Image'](
                    header=header(time_ns, cam.frame_id), height=img.shape[0], width=img.shape[1],
                    encoding='mono8', is_bigendian=0, step=img.shape[1], data=img.ravel())
            self._write(cam.input_topic, cam.input_type, msg, time_ns)
            self._write(cam.camera_info_topic, 'sensor_msgs/msg/CameraInfo',
                        camera_info(self.intrinsics[cam.name], cam.frame_id, time_ns), time_ns)

    def compressed(self, img, head):
        """A CompressedImage of the mono8 `img`, as image_transport's compressed plugin
        writes it (deterministic: the same image gives the same bytes)."""
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.image_codec == 'jpeg' else []
        ok, data = cv2.imencode('.jpg' if self.image_codec == 'jpeg' else '.png', img, params)
        if not ok:
            raise ValueError(f'{self.image_codec} encoding of a {img.shape} image failed')
        return TYPES['sensor_msgs/msg/CompressedImage'](
            header=head, format=f'mono8; {self.image_codec} compressed mono8', data=data.ravel())

    def write_odometry(self, topic: str, time_ns: int, T_odom_base, linear, angular,
                       pose_variance, twist_variance, frame='odom'):
        """Pose of base_link in `frame`, twist (linear, angular) in base_link; diagonal
        covariances from 6-vectors of variances (x, y, z, rot x, rot y, rot z)."""
        p = T_odom_base[:3, 3]
        pose = TYPES['geometry_msgs/msg/PoseWithCovariance'](
            pose=TYPES['geometry_msgs/msg/Pose'](
                position=TYPES['geometry_msgs/msg/Point'](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=quaternion(T_odom_base[:3, :3])),
            covariance=np.diag(np.asarray(pose_variance, float)).ravel())
        twist = TYPES['geometry_msgs/msg/TwistWithCovariance'](
            twist=TYPES['geometry_msgs/msg/Twist'](linear=vector3(linear), angular=vector3(angular)),
            covariance=np.diag(np.asarray(twist_variance, float)).ravel())
        msg = TYPES['nav_msgs/msg/Odometry'](header=header(time_ns, frame),
                                          child_frame_id=self.rig.base_frame, pose=pose, twist=twist)
        self._write(topic, 'nav_msgs/msg/Odometry', msg, time_ns)

    def write_imu(self, topic: str, time_ns: int, frame_id: str, gyro, accel,
                  gyro_variance: float, accel_variance: float, stamp_ns: int = None):
        """One sensor_msgs/Imu: angular velocity (rad/s) and specific force (m/s^2) in
        `frame_id`, diagonal covariances; no orientation (REP-145: covariance[0] = -1).
        stamp_ns: its header stamp when not its log time (a driver's stamps out of order)."""
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        msg = TYPES['sensor_msgs/msg/Imu'](
            header=header(time_ns if stamp_ns is None else stamp_ns, frame_id),
            orientation=TYPES['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=no_orientation,
            angular_velocity=vector3(gyro), angular_velocity_covariance=np.eye(3).ravel() * gyro_variance,
            linear_acceleration=vector3(accel),
            linear_acceleration_covariance=np.eye(3).ravel() * accel_variance)
        self._write(topic, 'sensor_msgs/msg/Imu', msg, time_ns)

    def close(self):
        self.bag.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def camera_info(intr, frame_id: str, time_ns: int):
    return TYPES['sensor_msgs/msg/CameraInfo'](
        header=header(time_ns, frame_id), height=int(intr.height), width=int(intr.width),
        distortion_model='plumb_bob', d=np.asarray(intr.D, float), k=intr.K.ravel(),
        r=np.eye(3).ravel(), p=intr.P.ravel(), binning_x=0, binning_y=0,
        roi=TYPES['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                   do_rectify=False))
