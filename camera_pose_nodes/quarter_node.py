"""Quarter node (paper task T_kl): KLT tracking and an EKF in one quarter of one camera.

Thin ROS shell over camera_pose_nodes.quarter_estimator.QuarterEstimator. Subscribes the
camera's image and CameraInfo and the general arbiter's fused pose (fed back for landmark
triangulation); publishes `pose` (PoseWithCovarianceStamped, base_link in odom, in its own
namespace /<cam>/q<l>) and its /diagnostics entry; with `debug_images`, also `tracks` (its
part of the image with its tracks drawn, for the camera arbiter's /<cam>/tracks: track_image).

Frame ordering: the estimate of frame t+1 needs the fused pose of frame t. An image that
arrives before that feedback waits (up to `feedback_timeout_s`), so that replay in lockstep
is deterministic and rate mode degrades gracefully instead of stalling. A fused pose that
comes before its frame's image (the general arbiter went ahead without this camera) is kept
and applied right after that image is processed.

Stereo pairs (the rig's stereo_pairs): the quarter also takes its partner camera's image and
CameraInfo, and applies the fused pose of frame t only with the partner's image of t (held
up to `partner_timeout_s`, then applied without, with a warning), as the sequential
pipeline does.
"""
import time
from collections import deque

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu, PointCloud2
from std_msgs.msg import Int64MultiArray

from camera_pose_nodes import kernel
from camera_pose_nodes.camera_model import intrinsics_from_msg
from camera_pose_nodes.frame_schedule import FrameSchedule, ScheduleBook
from camera_pose_nodes.map_scale import MapScaleCommand
from camera_pose_nodes.decoded_images import SHARED as DECODED
from camera_pose_nodes.gyro_steer import GyroSteer
from camera_pose_nodes.image_conversion import bgr8_message
from camera_pose_nodes.quarter_estimator import PARAMETERS, QuarterEstimator, QuarterParams, road_normal_of
from multicam_ego_motion.ros_plumbing import diagnostics
from multicam_ego_motion.ros_plumbing.bearing_messages import bearings_to_cdr
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.ros_plumbing.imu_messages import imu_gyro_from_cdr, imu_stamp_from_cdr
from multicam_ego_motion.ros_plumbing.node_main import spin_node
from multicam_ego_motion.ros_plumbing.node_parameters import declare_from_table
from multicam_ego_motion.ros_plumbing.pose_messages import estimate_to_msg, msg_to_estimate, stamp_to_ns
from multicam_ego_motion.ros_plumbing.qos import LATCHED, RELIABLE, RELIABLE_IMAGES, image_qos, imu_qos
from multicam_ego_motion.ros_plumbing.recent_outputs import RecentOutputs
from multicam_ego_motion.geometry.rig import load_rig, with_transport

# Timeouts only: the normal path is driven by messages. Every timer wake-up makes rclpy's
# executor rebuild its wait set over all of the worker's entities, so poll slowly.
POLL_PERIOD_S = 0.1
FUSED_AHEAD_KEPT = 4            # fused poses held for frames whose image has not come yet
IMAGE_TYPES = {'raw': Image, 'compressed': CompressedImage}   # a camera's transport (rig)

NODE_PARAMETERS = {
    'camera': ('front', 'name of the camera in the rig file', None, None),
    'quarter': (1, 'image quarter: 1 top-left, 2 top-right, 3 bottom-left, 4 bottom-right', 1, 4),
    'rig_file': ('', 'rig YAML (camera names, topics, extrinsics base_link -> optical)', None, None),
    'image_qos': ('sensor_data', 'image subscription QoS: sensor_data or reliable (lockstep replay)', None, None),
    'image_transport': ('', 'image_transport of this camera\'s images (and its stereo partner\'s): raw (sensor_msgs/Image on the image topic) or compressed (sensor_msgs/CompressedImage, JPEG or PNG, on <image topic>/compressed); empty: the rig file\'s transport for each camera', None, None),
    'fused_pose_topic': ('/ego_motion/fused_pose', 'general arbiter feedback topic', None, None),
    'feedback_timeout_s': (0.5, 'longest wait for the previous frame\'s fused pose', 0.0, 60.0),
    'frame_schedule_topic': ('/ego_motion/frame_schedule', 'which frames to process when the graph is behind the cameras (general arbiter)', None, None),
    'partner_timeout_s': (5.0, 'stereo pair: longest hold of a fused pose for the partner camera\'s image of its frame (then applied without stereo matches)', 0.0, 600.0),
    'map_scale_topic': ('/ego_motion/map_scale', 'map rescales of the general arbiter when a scale source appears (camera_pose_nodes/map_scale)', None, None),
    'road_normal_topic': ('/ego_motion/road_normal', "the general arbiter's road normal (base_link) at each frame over a road: the road points are put on it (road_normal)", None, None),
    'use_imu': (False, "subscribe to the rig's IMU (rig file `imu`, its topic) and start each frame's search, and the filter's predicted rotation, where its gyro turned the camera (gyro_steer), while the general arbiter uses the gyro (its use_imu: set both) and says its bias on gyro_bias_topic", None, None),
    'imu_qos': ('sensor_data', 'IMU subscription QoS: sensor_data (best effort, as drivers publish) or reliable (lockstep replay)', None, None),
    'imu_wait_s': (0.05, "use_imu: the longest an image waits for the gyro's samples up to its stamp (while the gyro is in use)", 0.0, 60.0),
    'gyro_bias_topic': ('/ego_motion/gyro_bias', "the general arbiter's gyro bias (base_link, rad/s) at each frame while it uses the gyro, not finite while it does not (a bad IMU): use_imu steers only while it is finite", None, None),
    'debug_images': (False, 'publish tracks (bgr8): this quarter\'s part of the image with its features, their flow and landmark/epipolar status drawn, which the camera arbiter (debug_images too) puts together into /<cam>/tracks; off: nothing drawn or published', None, None),
}


# The last fused pose decoded: a worker's shared feed hands the same message object to all
# its quarters (worker.py), which decoded it once each. Read-only, as it is shared.
_last_fused = (None, None)


def decode_fused(msg: PoseWithCovarianceStamped):
    global _last_fused
    if _last_fused[0] is not msg:
        est = msg_to_estimate(msg)
        est.T_odom_base.flags.writeable = False
        est.covariance.flags.writeable = False
        _last_fused = (msg, est)
    return _last_fused[1]


# The rig's gyro, one per process and IMU (topic, frame): every quarter of a worker steers by
# the same samples, each taken once (gyro_steer).
_GYRO_STEERS = {}


def shared_gyro_steer(rig) -> GyroSteer:
    key = (rig.imu.topic, rig.imu.frame_id, rig.imu.rotation.tobytes())
    if key not in _GYRO_STEERS:
        _GYRO_STEERS[key] = GyroSteer.for_rig(rig)
    return _GYRO_STEERS[key]


class QuarterNode(Node):
    def __init__(self, shared_inputs: bool = False, **node_kwargs):
        """shared_inputs: do not subscribe the image and the fused pose; a host (worker.py)
        that runs several quarters takes each once and calls on_image / on_fused of all."""
        super().__init__('quarter_node', **node_kwargs)
        p = declare_from_table(self, NODE_PARAMETERS)
        self.params = QuarterParams(**declare_from_table(self, PARAMETERS))
        if not p['rig_file']:
            raise UserError(f'{self.get_fully_qualified_name()}: parameter rig_file is required')
        rig = with_transport(load_rig(p['rig_file']), p['image_transport'],
                             f'{self.get_fully_qualified_name()}: parameter image_transport')
        self.camera = rig.camera(p['camera'])
        partners = rig.stereo_partners(self.camera.name) if self.params.stereo else []
        # the first partner: a quarter matches into one other image
        self.partner = rig.camera(partners[0]) if partners else None
        self.partner_intrinsics = None
        self.partner_images = {}        # stamp -> partner Image message, newest few
        self.held_fused = None          # (since, fused msg) waiting for the partner image
        self.partner_timeout_s = p['partner_timeout_s']
        self.floor_z = rig.floor_z
        self.road = rig.road_scale
        self.gyro = (shared_gyro_steer(rig) if p['use_imu'] and rig.imu is not None
                     and self.params.gyro_steer else None)
        self.imu_wait_s = p['imu_wait_s']
        self.raw_inputs = set()         # inputs taken as bytes (the IMU's samples)
        self.waits_for_gyro = False     # an image waits for the gyro's samples (on_imu drains)
        self.quarter = int(p['quarter'])
        self.source = f'{self.camera.name}/q{self.quarter}'
        self.feedback_timeout_s = p['feedback_timeout_s']
        self.scale_commands = []        # map rescales (map_scale), kept for a late CameraInfo
        self.road_normals = deque(maxlen=4)   # the newest road normals, kept for a late CameraInfo
        self.road_normal_error = None   # the last bad road normal said (not said again)
        self.schedule = ScheduleBook()  # frames skipped while the graph is behind (frame_schedule)
        self.skipped = 0                # images skipped since the last report
        self.estimator = None
        self.intrinsics = None
        self.info_error = None
        self.pending = deque()          # images waiting for the previous frame's fused pose
        self.last_processed_ns = None
        self.last_fused_ns = None
        # Fused poses of frames whose image has not come yet (the general arbiter went ahead
        # without this camera): applied once the image is processed, or it would wait for them
        # again (feedback_timeout_s, 60 s in lockstep) and drop out of the fusion.
        self.fused_ahead = {}           # stamp -> fused msg
        self.sent = RecentOutputs()     # stamp -> estimate, sent again for a re-published image
        self.on_frame_done = None       # hook(node) after a fused pose was applied (snapshots)
        # hook(stamp, DiagnosticStatus) instead of publishing: a worker batches the statuses
        # of its quarters into one /diagnostics message per frame (worker.py)
        self.diag_sink = None
        # hook(node) instead of working ahead at once: a worker runs node.work_ahead() when
        # none of its nodes has a message to handle (worker.py), so that it never delays them
        self.work_ahead_sink = None
        # hook(msg) after publishing an estimate: a worker hands it to a co-hosted camera
        # arbiter directly (which then does not subscribe to it)
        self.estimate_sink = None
        # debug_images: hook(msg) for the tracks tile, as estimate_sink (worker.py)
        self.tracks_sink = None
        self.pub_tracks = (self.create_publisher(Image, 'tracks', RELIABLE_IMAGES)
                           if p['debug_images'] else None)
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, 'pose', RELIABLE)
        # Without floor and stereo, and over a road, the general arbiter measures the scale
        # from every quarter's tracks (a wheel, when one comes, makes them unused)
        self.pub_bearings = (self.create_publisher(PointCloud2, 'bearings', RELIABLE)
                             if rig.sends_bearings else None)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE)
        # topic -> (type, QoS, callback) of the per-frame inputs
        # (the schedule first: an executor takes ready subscriptions in creation order)
        self.inputs = {p['frame_schedule_topic']: (Int64MultiArray, LATCHED, self.on_schedule),
                       p['map_scale_topic']: (Int64MultiArray, LATCHED, self.on_map_scale),
                       p['road_normal_topic']: (Vector3Stamped, RELIABLE, self.on_road_normal),
                       self.camera.input_topic: (IMAGE_TYPES[self.camera.transport],
                                                 image_qos(p['image_qos']), self.on_image),
                       p['fused_pose_topic']: (PoseWithCovarianceStamped, RELIABLE, self.on_fused)}
        if self.gyro is not None:
            # (the bias before the fused pose: when both wait, the executor takes them in
            # creation order, and the next frame steers by the bias of the frame before)
            self.inputs = {**{k: v for k, v in self.inputs.items() if k != p['fused_pose_topic']},
                           rig.imu.topic: (Imu, imu_qos(p['imu_qos']), self.on_imu),   # raw
                           p['gyro_bias_topic']: (Vector3Stamped, LATCHED, self.on_gyro_bias),
                           p['fused_pose_topic']: self.inputs[p['fused_pose_topic']]}
            self.raw_inputs = {rig.imu.topic}
        if self.partner is not None:
            self.inputs[self.partner.input_topic] = (IMAGE_TYPES[self.partner.transport],
                                                     image_qos(p['image_qos']), self.on_partner_image)
        if not shared_inputs:
            for topic, (msg_type, qos, callback) in self.inputs.items():
                self.create_subscription(msg_type, topic, callback, qos, raw=topic in self.raw_inputs)
        self.info_sub = self.create_subscription(CameraInfo, self.camera.camera_info_topic, self.on_info, RELIABLE)
        self.partner_info_sub = (None if self.partner is None else self.create_subscription(
            CameraInfo, self.partner.camera_info_topic, self.on_partner_info, RELIABLE))
        self.poll_timer = self.create_timer(POLL_PERIOD_S, self.poll)
        self.get_logger().info(f'{self.source}: waiting for {self.camera.input_topic} '
                               f'({kernel.selected()} kernel)')

    # --- inputs -------------------------------------------------------------------------
    def on_info(self, msg: CameraInfo):
        if self.intrinsics is not None:
            return
        try:
            self.intrinsics = intrinsics_from_msg(msg, self.camera.name)
        except (UserError, ValueError) as e:
            if self.info_error != str(e):
                self.info_error = str(e)
                self.get_logger().error(f'{self.source}: bad CameraInfo on {self.camera.camera_info_topic}: {e}')
                self.publish_diag(None, 'error', f'bad CameraInfo: {e}')
            return
        self.estimator = QuarterEstimator(self.camera, self.quarter, self.intrinsics, self.params,
                                          (msg.width, msg.height), self.floor_z, self.road)
        self.estimator.gyro = self.gyro
        for command in self.scale_commands:
            self.estimator.rescale_command(command)
        for stamp_ns, up in self.road_normals:
            self.estimator.add_road_normal(stamp_ns, up)
        self.connect_partner()
        self.stop_camera_info()

    def on_partner_info(self, msg: CameraInfo):
        if self.partner_intrinsics is not None:
            return
        try:
            self.partner_intrinsics = intrinsics_from_msg(msg, self.partner.name)
        except (UserError, ValueError) as e:
            self.get_logger().error(f'{self.source}: bad CameraInfo of stereo partner '
                                    f'{self.partner.name}: {e}', throttle_duration_sec=5.0)
            return
        if self.partner_info_sub is not None:
            self.destroy_subscription(self.partner_info_sub)
            self.partner_info_sub = None
        self.connect_partner()
        self.apply_held()

    def connect_partner(self):
        if (self.estimator is not None and self.partner_intrinsics is not None
                and not self.estimator.wants_partner_image):
            self.estimator.set_partner(self.partner, self.partner_intrinsics)

    def on_partner_image(self, msg: Image):
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self.last_fused_ns is not None and stamp_ns <= self.last_fused_ns:
            return                      # its frame's fused pose went ahead without it
        self.partner_images[stamp_ns] = msg
        while len(self.partner_images) > 8:
            del self.partner_images[min(self.partner_images)]
        self.apply_held()

    def stop_camera_info(self):
        # Only the first good CameraInfo is used, and drivers (and bags) repeat it with every
        # image: 16 quarters taking and decoding it every frame were ~8 executor callbacks
        # per worker and frame for nothing.
        if self.info_sub is not None:
            self.destroy_subscription(self.info_sub)
            self.info_sub = None

    def on_image(self, msg: Image):
        # A frame delivered twice (the player re-publishes the current frame after a worker
        # restart, for the nodes that lost it) is processed once.
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if any(stamp_to_ns(m.header.stamp) == stamp_ns for _, m in self.pending):
            # (reported like one that came after its frame was processed: which of the two
            # it is depends only on how far the quarter had got)
            self.publish_diag(msg.header.stamp, 'warn',
                              f'image dropped: stamp {stamp_ns / 1e9:.6f} s is already waiting '
                              'to be processed (duplicate or out of order)')
            return
        if self.last_processed_ns is not None and stamp_ns <= self.last_processed_ns:
            sent = self.sent.get(stamp_ns)
            if sent is not None:
                # A re-published frame (a worker was restarted): the estimate again, for
                # restored nodes downstream that lost it (the others drop the copy).
                self.send_estimate(estimate_to_msg(sent))
            self.report_stale(msg, stamp_ns)
            return
        self.schedule.saw(stamp_ns)    # (its camera's period, for the schedule)
        if not self.schedule.takes(stamp_ns):
            self.skipped += 1          # the graph is behind: a frame every quarter skips
            return
        self.pending.append((time.monotonic(), msg))
        self.drain()
        self.offer_work_ahead()

    def on_schedule(self, msg: Int64MultiArray):
        try:
            self.schedule.add(FrameSchedule.from_list(msg.data))
        except ValueError as e:
            self.get_logger().error(f'{self.source}: frame schedule ignored: {e}')
            return
        # frames that waited under the previous schedule
        kept = [(t, m) for t, m in self.pending if self.schedule.takes(stamp_to_ns(m.header.stamp))]
        self.skipped += len(self.pending) - len(kept)
        self.pending = deque(kept)

    def on_map_scale(self, msg: Int64MultiArray):
        try:
            command = MapScaleCommand.from_list(msg.data)
        except ValueError as e:
            self.get_logger().error(f'{self.source}: map-scale command ignored: {e}')
            return
        self.scale_commands.append(command)
        if self.estimator is not None:
            self.estimator.rescale_command(command)

    def on_road_normal(self, msg: Vector3Stamped):
        stamp_ns = stamp_to_ns(msg.header.stamp)
        # Checked here, normalised once by the estimator (add_road_normal), as the sequential
        # pipeline hands it over: normalised twice, its last bits differed from the pipeline's.
        up = (msg.vector.x, msg.vector.y, msg.vector.z)
        try:
            road_normal_of(up, self.source)
        except UserError as e:
            if self.road_normal_error != str(e):
                self.road_normal_error = str(e)
                self.get_logger().error(f'{e}: ignored (the last good one stays in use)')
            return
        self.road_normals.append((stamp_ns, up))
        if self.estimator is not None:
            self.estimator.add_road_normal(stamp_ns, up)

    def on_imu(self, data: bytes):
        # As bytes (raw subscription): the process's quarters share one GyroSteer, and all but
        # the first to get a sample see from its stamp alone that it is in. (The arbiter says
        # what is wrong with a bad sample; here it is only not used.)
        stamp_ns = imu_stamp_from_cdr(data)
        if stamp_ns is None or self.gyro.is_new(stamp_ns):
            try:
                stamp_ns, frame_id, gyro = imu_gyro_from_cdr(data)
            except ValueError:
                pass
            else:
                self.gyro.add(stamp_ns, frame_id, gyro)
        if self.waits_for_gyro and self.pending and self.gyro_ready(self.pending[0][1], self.pending[0][0]):
            self.drain()
            self.offer_work_ahead()

    def on_gyro_bias(self, msg: Vector3Stamped):
        self.gyro.set_bias(stamp_to_ns(msg.header.stamp), (msg.vector.x, msg.vector.y, msg.vector.z))

    def gyro_ready(self, msg, arrived) -> bool:
        """The gyro's samples up to the image's stamp are in (its search and prediction
        follow them), or the gyro is not used, or the image waited imu_wait_s for them."""
        ready = (self.gyro is None or self.gyro.settled(stamp_to_ns(msg.header.stamp))
                 or time.monotonic() - arrived > self.imu_wait_s)
        self.waits_for_gyro = not ready
        return ready

    def on_fused(self, msg: PoseWithCovarianceStamped):
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self.estimator is not None and not self.estimator.takes_feedback(stamp_ns):
            if self.last_processed_ns is not None and stamp_ns > self.last_processed_ns:
                self.hold_fused_ahead(stamp_ns, msg)
            return                      # (else another camera's capture time: free-running cameras)
        if self.partner is not None and self.estimator is not None:
            # Stereo: applied with the partner's image of the same frame (apply_held), as
            # the sequential pipeline does, whichever of the two arrives first
            if self.held_fused is not None:
                self.apply_fused(self.held_fused[1], None)
            self.held_fused = (time.monotonic(), msg)
            self.apply_held()
            return
        self.apply_fused(msg, None)

    def apply_held(self, timed_out=False):
        if self.held_fused is None:
            return
        since, msg = self.held_fused
        stamp_ns = stamp_to_ns(msg.header.stamp)
        image = self.partner_images.get(stamp_ns)
        if self.partner_intrinsics is None or image is None:
            if not timed_out:
                return
            what = (f'CameraInfo on {self.partner.camera_info_topic}' if self.partner_intrinsics is None
                    else f'image on {self.partner.input_topic}')
            self.get_logger().warning(
                f'{self.source}: no stereo partner {what} for frame {stamp_ns / 1e9:.6f} s after '
                f'{self.partner_timeout_s} s: fused pose applied without stereo matches')
            self.publish_diag(msg.header.stamp, 'warn', f'stereo partner {what} missing for this frame')
        self.held_fused = None
        gray = image if isinstance(image, np.ndarray) else None
        if gray is None and image is not None and self.partner_intrinsics is not None:
            try:
                gray = self.gray(self.partner, image, (self.partner_intrinsics.width,
                                                       self.partner_intrinsics.height))
            except (UserError, ValueError) as e:
                self.get_logger().error(f'{self.source}: stereo partner image on '
                                        f'{self.partner.input_topic} rejected: {e}',
                                        throttle_duration_sec=5.0)
        for k in [k for k in self.partner_images if k <= stamp_ns]:
            del self.partner_images[k]
        self.apply_fused(msg, gray)

    def hold_fused_ahead(self, stamp_ns: int, msg):
        # Also what free-running cameras' other capture times look like: those are dropped
        # when this quarter's next own frame is processed (apply_fused_ahead).
        self.fused_ahead[stamp_ns] = msg
        while len(self.fused_ahead) > FUSED_AHEAD_KEPT:
            del self.fused_ahead[min(self.fused_ahead)]

    def apply_fused_ahead(self, stamp_ns: int):
        """After frame `stamp_ns` was processed: its fused pose if it came before its image."""
        if not self.fused_ahead:
            return
        msg = None
        for k in [k for k in self.fused_ahead if k <= stamp_ns]:
            m = self.fused_ahead.pop(k)
            if k == stamp_ns:
                msg = m
        if msg is not None:
            self.get_logger().warning(
                f'{self.source}: the fused pose of frame {stamp_ns / 1e9:.6f} s came before its image '
                '(fused without this camera): applied after the image', throttle_duration_sec=5.0)
            self.on_fused(msg)

    def apply_fused(self, msg: PoseWithCovarianceStamped, partner_gray):
        fused = decode_fused(msg)
        if self.estimator is not None and not self.estimator.takes_feedback(fused.stamp_ns):
            return                      # another camera's capture time (free-running cameras)
        self.last_fused_ns = fused.stamp_ns
        if self.estimator is not None:
            self.estimator.apply_fused_pose(fused.stamp_ns, fused.T_odom_base, fused.covariance,
                                            partner_gray)
            self.publish_new_bearings()
            if self.on_frame_done is not None:
                self.on_frame_done(self)
        self.drain()
        self.offer_work_ahead()

    # --- processing ---------------------------------------------------------------------
    def poll(self):
        """Timeouts (feedback, missing CameraInfo); called every POLL_PERIOD_S by the node's
        own timer, or by its worker's one timer for all its nodes (worker.py)."""
        if self.held_fused is not None and time.monotonic() - self.held_fused[0] > self.partner_timeout_s:
            self.apply_held(timed_out=True)
        self.drain()

    def ready_for_next(self, first_wait) -> bool:
        if self.last_processed_ns is None:
            return True
        if self.last_fused_ns is not None and self.last_fused_ns >= self.last_processed_ns:
            return True
        if not self.schedule.takes(self.last_processed_ns):
            return True     # taken before the schedule came: no fused pose will come for it
        return time.monotonic() - first_wait > self.feedback_timeout_s

    def drain(self):
        while self.pending:
            arrived, msg = self.pending[0]
            if self.estimator is None:
                if self.intrinsics is None and time.monotonic() - arrived > 2.0:
                    self.pending.popleft()
                    # Keep naming the actual problem: a CameraInfo that came but was unusable.
                    why = (f'bad CameraInfo: {self.info_error}' if self.info_error
                           else f'no CameraInfo on {self.camera.camera_info_topic}')
                    self.publish_diag(msg.header.stamp, 'error', f'{why}: image dropped')
                    continue
                return
            if not self.ready_for_next(arrived) or not self.gyro_ready(msg, arrived):
                return
            _, msg = self.pending.popleft()
            self.process(msg)

    def can_prefetch(self) -> bool:
        return (self.estimator is not None and bool(self.pending)
                and not self.estimator.prefetched(stamp_to_ns(self.pending[0][1].header.stamp))
                and not self.ready_for_next(self.pending[0][0])
                and self.gyro_ready(self.pending[0][1], self.pending[0][0]))

    def offer_work_ahead(self):
        if self.estimator is not None and (self.estimator.extraction_due() or self.can_prefetch()):
            if self.work_ahead_sink is not None:
                self.work_ahead_sink(self)
            else:
                self.work_ahead()

    def work_ahead(self):
        """What can be done before it is needed: the last frame's new features (the estimate
        is out already), then the next image's optical flow."""
        if self.estimator is not None:
            self.estimator.extract_pending()
        self.prefetch()
        self.publish_new_bearings()

    def publish_new_bearings(self):
        """The features extracted since the last call, at their first frame (QuarterEstimator.new_bearings),
        when this quarter sends its tracks."""
        nb = self.estimator.new_bearings() if self.estimator is not None else None
        if nb is not None and self.pub_bearings is not None:
            self.pub_bearings.publish(bearings_to_cdr(nb[0], self.camera.frame_id, *nb[1:]))

    def prefetch(self):
        """Pipelining: while this quarter waits for the fused pose of its last frame, the
        next image's optical flow (which does not depend on it) is computed already."""
        if not self.can_prefetch():
            return
        msg = self.pending[0][1]
        stamp_ns = stamp_to_ns(msg.header.stamp)
        try:
            gray = self.gray(self.camera, msg, self.estimator.image_size)
            self.estimator.prefetch(stamp_ns, gray)
        except (UserError, ValueError):
            pass              # process() reports it when the image's turn comes

    @staticmethod
    def gray(camera, msg, expected_size):
        """The image as gray, decoded once for every quarter of this process (decoded_images)."""
        return DECODED.gray(camera.input_topic, stamp_to_ns(msg.header.stamp), msg, expected_size,
                            camera.mono16_bits)

    def report_stale(self, msg, stamp_ns):
        # A duplicate or late image would run the tracker and the filter backwards in time.
        self.publish_diag(msg.header.stamp, 'warn',
                          f'image dropped: stamp {stamp_ns / 1e9:.6f} s is not after the last '
                          f'processed {self.last_processed_ns / 1e9:.6f} s (duplicate or out of order)')

    def process(self, msg: Image):
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self.last_processed_ns is not None and stamp_ns <= self.last_processed_ns:
            self.report_stale(msg, stamp_ns)
            return
        gray = None
        if not self.estimator.prefetched(stamp_ns):
            try:
                gray = self.gray(self.camera, msg, self.estimator.image_size)
            except (UserError, ValueError) as e:
                self.get_logger().error(f'{self.source}: image on {self.camera.input_topic} rejected: {e}',
                                        throttle_duration_sec=5.0)
                self.publish_diag(msg.header.stamp, 'error', f'image on {self.camera.input_topic} rejected: {e}')
                return
        est = self.estimator.process_image(stamp_ns, gray)
        self.last_processed_ns = stamp_ns
        self.publish_new_bearings()      # (the last frame's, if process_image extracted them)
        if self.pub_bearings is not None:
            self.pub_bearings.publish(bearings_to_cdr(stamp_ns, self.camera.frame_id,
                                                      *self.estimator.bearings()))
        self.sent.add(stamp_ns, est)
        msg = estimate_to_msg(est)
        # Status before the estimate: a co-hosted arbiter chain may fuse the frame and save
        # the general arbiter's snapshot inside send_estimate, and a worker's batch of this
        # frame's statuses goes out only when complete: a crash right after the snapshot lost it.
        self.publish_diag(msg.header.stamp, 'ok' if est.state == 'tracking' else 'warn', est.state, est)
        self.send_estimate(msg)
        if self.pub_tracks is not None:
            self.publish_tracks(msg.header.stamp, est)
        self.apply_fused_ahead(stamp_ns)

    def send_estimate(self, msg):
        # With its camera arbiter co-hosted, published only for other listeners (a recorder,
        # a viewer): a publish without subscribers still cost ~0.2 ms.
        if self.estimate_sink is None or self.pub_pose.get_subscription_count() > 0:
            self.pub_pose.publish(msg)
        if self.estimate_sink is not None:
            self.estimate_sink(msg)

    def publish_tracks(self, stamp, est):
        """debug_images: this frame's tile (track_image.quarter_tile), after the estimate
        went out; drawn only when someone takes it."""
        if self.tracks_sink is None and self.pub_tracks.get_subscription_count() == 0:
            return
        from camera_pose_nodes.track_image import TRAIL, quarter_tile
        e = self.estimator
        try:
            trails, status = e.track_overlay(TRAIL)
            tile = quarter_tile(e.tracker.prev_crop, e.region, trails, status,
                                [f'q{self.quarter} {est.state}',
                                 f'in {est.n_inliers}/{est.n_features} lm {est.n_landmarks}'])
        except Exception as ex:   # a debug picture must never stop the odometry
            self.get_logger().error(f'{self.source}: tracks image not drawn: {type(ex).__name__}: {ex}',
                                    throttle_duration_sec=5.0)
            return
        msg = bgr8_message(Image(), tile, stamp, self.camera.frame_id)
        if self.pub_tracks.get_subscription_count() > 0:
            self.pub_tracks.publish(msg)
        if self.tracks_sink is not None:
            self.tracks_sink(msg)

    # --- hand-over between workers (coordinator) ------------------------------------------
    def idle(self) -> bool:
        """Between frames: nothing pending and the last frame's fused pose applied."""
        return not self.pending and self.held_fused is None and (self.last_processed_ns is None or (
            self.last_fused_ns is not None and self.last_fused_ns >= self.last_processed_ns))

    def get_state(self):
        """Picklable state (None before CameraInfo): the estimator's and this shell's."""
        if self.estimator is None:
            return None
        return {'estimator': self.estimator.get_state(), 'intrinsics': self.intrinsics,
                'image_size': self.estimator.image_size,
                'last_processed_ns': self.last_processed_ns, 'last_fused_ns': self.last_fused_ns,
                'schedule': self.schedule.get_state(), 'sent': self.sent.get_state(),
                # stereo: the partner's CameraInfo and the images that came ahead of their frame
                'partner_intrinsics': self.partner_intrinsics,
                'partner_images': self.partner_grays()}

    def partner_grays(self):
        """The partner images waiting for their frame, as arrays (picklable)."""
        if self.partner_intrinsics is None:
            return {}
        size = (self.partner_intrinsics.width, self.partner_intrinsics.height)
        out = {}
        for k, m in self.partner_images.items():
            try:
                out[k] = m if isinstance(m, np.ndarray) else self.gray(self.partner, m, size)
            except (UserError, ValueError):
                pass
        return out

    def set_state(self, s):
        self.intrinsics = s['intrinsics']
        self.estimator = QuarterEstimator(self.camera, self.quarter, self.intrinsics, self.params,
                                          tuple(s['image_size']), self.floor_z, self.road)
        self.estimator.gyro = self.gyro
        self.estimator.set_state(s['estimator'])
        if s.get('partner_intrinsics') is not None and self.partner is not None:
            self.partner_intrinsics = s['partner_intrinsics']
            if self.partner_info_sub is not None:
                self.destroy_subscription(self.partner_info_sub)
                self.partner_info_sub = None
            self.connect_partner()
        self.partner_images.update(s.get('partner_images') or {})
        self.stop_camera_info()
        self.last_processed_ns = s['last_processed_ns']
        self.last_fused_ns = s['last_fused_ns']
        self.schedule.set_state(s['schedule'])
        self.sent.set_state(s.get('sent'))

    def publish_diag(self, stamp, level, message, est=None):
        values = {}
        if est is not None:
            values = {'state': est.state, 'features': est.n_features, 'landmarks': est.n_landmarks,
                      'floor_landmarks': est.n_floor, 'inliers': est.n_inliers,
                      'road_warp_tracks': self.estimator.tracker.last_recovered,
                      'images_skipped': self.skipped}
            self.skipped = 0
            values.update({f'{k}_ms': float(v) for k, v in est.stage_ms.items()})
        if stamp is None:
            stamp = self.get_clock().now().to_msg()
        status = diagnostics.status(f'ego_motion/{self.source}', level, message, values,
                                    hardware_id=self.camera.name)
        diagnostics.emit(stamp, status, self.diag_sink, self.pub_diag)


def main(args=None):
    return spin_node(QuarterNode, 'quarter_node', args)
