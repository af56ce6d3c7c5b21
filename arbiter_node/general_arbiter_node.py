"""General arbiter (paper task T_5 / T_GA): median filter across cameras, metric scale, its
own EKF; publishes /odom, TF odom -> base_link, /ego_motion/path and feeds the fused pose
back to the quarter nodes (/ego_motion/fused_pose) for landmark triangulation.

Thin ROS shell over arbiter_node.general_fusion.GeneralFusion. The feedback is published
before /odom: a lockstep player waits for /odom, so by then every quarter has the feedback
in flight.
"""
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import Imu, PointCloud2
from rclpy.node import Node
from std_msgs.msg import Int64MultiArray
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from arbiter_node.capture_spread import WindowLearner
from arbiter_node.general_fusion import PARAMETERS as FUSION_PARAMETERS
from camera_pose_nodes.frame_schedule import FrameGovernor, ScheduleBook
from arbiter_node.general_fusion import GeneralFusion
from arbiter_node.path_history import PathHistory
from arbiter_node.stamp_sync import StampSynchronizer
from arbiter_node.wheel_prior import WheelBuffer, twist_from_odometry
from camera_pose_nodes.pose_estimate import PoseEstimate
from multicam_ego_motion.coordinator.allocation import QUARTERS
from multicam_ego_motion.coordinator.graph_spec import bearings_topic
from multicam_ego_motion.ros_plumbing import diagnostics
from multicam_ego_motion.ros_plumbing.bearing_messages import bearings_from_cdr
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.ros_plumbing.lean_node import subscribe_remote
from multicam_ego_motion.ros_plumbing.node_main import spin_node
from multicam_ego_motion.ros_plumbing.node_parameters import declare_from_table
from multicam_ego_motion.ros_plumbing.pose_messages import (covariance_field, estimate_to_msg, fill_pose,
                                               msg_to_estimate, ns_to_stamp, stamp_to_ns,
                                               transform_msg)
from multicam_ego_motion.ros_plumbing.imu_messages import imu_sample_from_cdr
from multicam_ego_motion.ros_plumbing.qos import LATCHED, RELIABLE, imu_qos
from multicam_ego_motion.geometry.rig import load_rig
from multicam_ego_motion.geometry.se3 import is_valid_covariance

# Timeouts only: the normal path is driven by messages. Every timer wake-up makes rclpy's
# executor rebuild its wait set over all of the worker's entities, so poll slowly.
POLL_PERIOD_S = 0.1

NODE_PARAMETERS = {
    'rig_file': ('', 'rig YAML (camera names, topics, extrinsics base_link -> optical)', None, None),
    'odom_frame': ('odom', 'REP-105 odometry frame', None, None),
    'base_frame': ('base_link', 'REP-105 robot body frame', None, None),
    'publish_tf': (True, 'broadcast odom -> base_link on /tf', None, None),
    'use_wheel_odometry': (True, 'fuse /wheel/odom as a body-twist prior when it is published', None, None),
    'wheel_odometry_topic': ('/wheel/odom', 'wheel odometry (nav_msgs/Odometry)', None, None),
    'sync_timeout_s': (0.5, 'longest wait for all cameras of one frame', 0.0, 60.0),
    'sync_window_s': (0.0, 'optional grouping of free-running cameras: estimates whose stamps lie within this of one another are one frame, fused at its latest stamp (each moved there with the EKF\'s twist); 0 (default) = estimates with identical stamps are fused together and every other one at its own stamp, in stamp order, which suits any phase and any mix of rates. A lockstep player must group frames by the same window', 0.0, 1.0),
    'learn_sync_window': (False, 'with sync_window_s 0: learn the window from the cameras\' first estimates (arbiter_node/capture_spread) when their stamps differ, use it from then on and say which sync_window_s to set', None, None),
    'wheel_wait_s': (0.5, 'then the longest wait for the wheel reading of that frame (while a wheel publisher is connected)', 0.0, 60.0),
    'imu_wait_s': (0.05, 'with the rig\'s IMU (use_imu): the longest wait for its samples up to a frame\'s stamp (while an IMU publisher is connected)', 0.0, 60.0),
    'tracks_wait_s': (0.05, 'free-running cameras (lone_camera_track_rotation): the longest wait for the tracks of a camera fused alone at its stamp, from its quarters', 0.0, 60.0),
    'imu_qos': ('sensor_data', 'IMU subscription QoS: sensor_data (best effort, as drivers publish) or reliable (lockstep replay)', None, None),
    'path_max_poses': (5000, 'poses kept on /ego_motion/path (oldest dropped)', 1, 1000000),
    'path_min_spacing_m': (0.05, '/ego_motion/path keeps a pose every this many metres', 0.0, 100.0),
    'path_min_turn_rad': (0.1, '... or every this much rotation', 0.0, 3.15),
    'path_publish_period_s': (1.0, '/ego_motion/path is republished at most this often (stamp time; it costs ~10 us per pose)', 0.0, 3600.0),
    'odom_rate_hz': (0.0, '/odom, /tf and /ego_motion/path: 0 = after every fused update (each camera stamp of free-running cameras, each frame of a synchronised rig); > 0 = at most this often, each with the newest state and its stamp (lockstep replay sets 0: the player waits for /odom)', 0.0, 1000.0),
    'max_lag_s': (0.25, 'live: when the fused poses lag their frames by more than this, the quarters process only as many frames as the graph keeps up with, evenly spread (7 of 8 ... 1 of 6) until they catch up (/ego_motion/frame_schedule; /diagnostics achieved_rate_hz against camera_rate_hz); 0 processes every frame (lockstep replay)', 0.0, 10.0),
}


class GeneralArbiterNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('general_arbiter', **node_kwargs)
        p = declare_from_table(self, NODE_PARAMETERS)
        fusion_params = declare_from_table(self, FUSION_PARAMETERS)
        if not p['rig_file']:
            raise UserError('general_arbiter: parameter rig_file is required')
        self.rig = load_rig(p['rig_file'])
        self.p = p
        self.fusion = GeneralFusion(self.rig, fusion_params)
        self.sync = StampSynchronizer(self.rig.names, p['sync_timeout_s'],
                                      window_ns=int(round(p['sync_window_s'] * 1e9)),
                                      takes=self.schedule_takes)
        # Free-running cameras on a rig configured as synchronised: every image would be a
        # frame of its own (fused alone, after the sync timeout).
        self.window_learner = (WindowLearner() if p['learn_sync_window'] and self.sync.window_ns == 0
                               else None)
        self.wheel = WheelBuffer()
        self.path = PathHistory(p['path_min_spacing_m'], p['path_min_turn_rad'], p['path_max_poses'],
                                p['path_publish_period_s'])
        self.last_odom_ns = None              # stamp of the last /odom (odom_rate_hz)
        self.on_frame_done = None            # hook(node) after a frame was published (snapshots)
        self.diag_sink = None                # hook(stamp, status): the worker batches statuses per frame
        self.governor = FrameGovernor(p['max_lag_s'])
        self.issued = ScheduleBook()         # the schedules published, for the frames they skip
        self.off_schedule = 0                # camera estimates of skipped frames, left out
        self.tracks_timed_out = 0            # lone cameras' frames fused without their tracks (tracks_wait_s)
        # Latched: a quarter that starts or moves later still gets the schedule in force.
        self.pub_schedule = self.create_publisher(Int64MultiArray, '/ego_motion/frame_schedule', LATCHED)
        # Latched too: map rescales (map_scale), each applied from a given frame on.
        self.pub_map_scale = self.create_publisher(Int64MultiArray, '/ego_motion/map_scale', LATCHED)
        self.map_scale_epoch = 0
        # Over a road: the road's normal the quarters put their road points on (road_normal)
        self.pub_road_normal = self.create_publisher(Vector3Stamped, '/ego_motion/road_normal', RELIABLE)
        # With the IMU: the gyro's bias for the quarters' steering (gyro_steer), not finite
        # while the gyro is out; latched, for a quarter that starts or moves later
        self.pub_gyro_bias = (self.create_publisher(Vector3Stamped, '/ego_motion/gyro_bias', LATCHED)
                              if self.fusion.wants_imu() else None)
        self.pub_fused = self.create_publisher(PoseWithCovarianceStamped, '/ego_motion/fused_pose', RELIABLE)
        self.pub_odom = self.create_publisher(Odometry, '/odom', RELIABLE)
        self.pub_tf = self.create_publisher(TFMessage, '/tf', RELIABLE)
        self.pub_path = self.create_publisher(Path, '/ego_motion/path', RELIABLE)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE)
        self.camera_subs = {}
        self.take_local(())
        self.held = []                       # (sync group, since): waiting for its wheel reading (IMU, tracks)
        self.imu_sub = None
        self.imu_error = None                # the last problem said of the IMU (not said again)
        self.imu_unreadable = 0              # samples whose bytes did not read as sensor_msgs/Imu
        self.imu_said = ('ok', None)         # the IMU health's (state, problem) last logged
        if self.fusion.wants_imu():
            # (as bytes, read by wire_types: 200 samples a second)
            self.imu_sub = self.create_subscription(Imu, self.rig.imu.topic, self.on_imu,
                                                    imu_qos(p['imu_qos']), raw=True)
        self.wheel_sub = None
        if p['use_wheel_odometry']:
            self.wheel_sub = self.create_subscription(Odometry, p['wheel_odometry_topic'],
                                                      self.on_wheel, RELIABLE)
        # Every quarter's tracks: without stereo and floor for the scale (scale_state), with a
        # gyro for its bias, from free-running cameras for their rotations
        self.bearing_subs = [] if not self.fusion.wants_bearings() else [
            self.create_subscription(PointCloud2, bearings_topic(n, q),
                                     lambda m, n=n, q=q: self.on_bearings(n, q, m), RELIABLE, raw=True)
            for n in self.rig.names for q in range(1, QUARTERS + 1)]
        self.create_service(Trigger, '~/reset', self.on_reset)
        self.poll_timer = self.create_timer(POLL_PERIOD_S, self.poll)
        self.get_logger().info(f'fusing cameras {", ".join(self.rig.names)}')

    def take_local(self, local):
        """Cameras whose estimates a host hands to on_camera itself (worker.py: co-hosted
        camera arbiters): no subscription for them, every other one subscribed."""
        subscribe_remote(self, self.camera_subs, self.rig.names, local, lambda n: self.create_subscription(
            PoseWithCovarianceStamped, f'/{n}/pose', lambda m: self.on_camera(n, m), RELIABLE))

    def on_wheel(self, msg: Odometry):
        self.wheel.add(stamp_to_ns(msg.header.stamp), *twist_from_odometry(msg))
        self.fuse_held()

    def on_imu(self, data: bytes):
        try:
            s = imu_sample_from_cdr(data)
        except ValueError as e:
            problem = f'sample not used: {e}'
            self.imu_unreadable += 1
        else:
            problem = self.fusion.add_imu(s.stamp_ns, s.gyro, s.gyro_covariance, s.frame_id,
                                          s.accel, s.accel_covariance)
        if problem is not None and problem != self.imu_error:
            self.get_logger().error(f'{self.rig.imu.topic}: {problem}', throttle_duration_sec=5.0)
        self.imu_error = problem
        self.fuse_held()

    def imu_status(self):
        """The IMU's health for /diagnostics (None without one), its changes logged once."""
        health = self.fusion.imu_health
        if health is None:
            return None
        level, message, values = health.status()
        values['imu_publishers'] = self.imu_sub.get_publisher_count() if self.imu_sub is not None else 0
        bias = self.fusion.ekf.gyro_bias
        values['gyro_bias_rad_s'] = ' '.join(f'{b:+.5f}' for b in bias)
        values['gyro_bias_fixes'] = self.fusion.bias_fixes     # measured from the tracks
        values['accel_bias_m_s2'] = ' '.join(f'{b:+.4f}' for b in self.fusion.ekf.accel_bias)
        values['gravity_fixes'] = self.fusion.gravity_fixes   # frame steps whose accelerometer measured up
        values['imu_unreadable'] = self.imu_unreadable
        if (health.state, health.problem) != self.imu_said:
            self.imu_said = (health.state, health.problem)
            # (a call site per severity: rclpy refuses one site that changes its severity)
            said = f'{self.rig.imu.topic}: {message}'
            if level == 'error':
                self.get_logger().error(said)
            elif level == 'warn':
                self.get_logger().warning(said)
            else:
                self.get_logger().info(said)
        return level, message, values

    def imu_settled(self, stamp_ns) -> bool:
        # As the wheel: the gyro's samples up to the frame, whichever callback came first
        return (self.imu_sub is None or self.imu_sub.get_publisher_count() == 0
                or self.fusion.imu_settled(stamp_ns))

    def on_bearings(self, camera, quarter, data: bytes):
        try:
            stamp_ns, ids, xy, sigma = bearings_from_cdr(data)
        except ValueError as e:
            self.get_logger().error(f'{bearings_topic(camera, quarter)}: {e}', throttle_duration_sec=5.0)
            return
        self.fusion.add_bearings(camera, quarter, stamp_ns, ids, xy, sigma)
        if self.held:
            self.fuse_held()

    def wheel_settled(self, stamp_ns) -> bool:
        # A frame whose cameras are all in is fused once its wheel reading is in too: fusing
        # it with the previous reading depended on which callback the executor took first
        # (a lockstep replay once differed from another in frame 13).
        return (self.wheel_sub is None or self.wheel_sub.get_publisher_count() == 0
                or self.wheel.settled(stamp_ns))

    def on_camera(self, name, msg):
        est = msg_to_estimate(msg, source=name)
        if self.window_learner is not None:
            self.learn_window(name, est.stamp_ns)
        if not self.schedule_takes(name, est.stamp_ns):
            # A frame the schedule skips, from a camera whose quarters took it before the
            # schedule reached them: the others skipped it, and fusing it would give /odom
            # from part of the rig. (Its quarters do not wait for its fused pose: theirs
            # skips it too by now.)
            self.sync.saw(name, est.stamp_ns)
            self.off_schedule += 1
            return
        self.release(self.sync.add(name, est.stamp_ns, est, time.monotonic()))

    def schedule_takes(self, camera, stamp_ns) -> bool:
        """Whether the quarters of this camera take its frame at this stamp (each counts its
        camera's own frames: ScheduleBook)."""
        return self.issued.takes(stamp_ns, self.sync.period_ns.get(camera))

    def frame_period_ns(self):
        """The cameras' frame period: the shortest of their own (free-running cameras'
        estimates are fused at their own stamps, several per frame period)."""
        return min(self.sync.period_ns.values(), default=None)

    def learn_window(self, name, stamp_ns):
        spread = self.window_learner.add(name, stamp_ns)
        if spread is None:
            return
        self.window_learner = None
        window, said = spread.verdict()
        if window:
            self.sync.window_ns = int(round(window * 1e9))
            said += ' from now on (set sync_window_s to that)'
        if said:
            self.get_logger().warn(said)

    def on_reset(self, request, response):
        self.fusion.reset()
        self.path.reset()
        response.success = True
        response.message = 'general arbiter reset: odometry restarts at the origin'
        self.get_logger().warn(response.message)
        return response

    def poll(self):
        """Sync timeouts; called every POLL_PERIOD_S by the node's own timer, or by its
        worker's one timer for all its nodes (worker.py)."""
        self.release(self.sync.poll(time.monotonic()))

    def release(self, groups):
        now = time.monotonic()
        self.held.extend((g, now) for g in groups)
        self.fuse_held()

    def fuse_held(self):
        while self.held:
            g, since = self.held[0]
            # The wheel reading at the frame's first capture (free-running cameras: the wheel
            # ticks with the frame clock, and a later reading only comes with the next frame).
            if not self.wheel_settled(g.first_ns) and time.monotonic() - since < self.p['wheel_wait_s']:
                return
            if not self.imu_settled(g.stamp_ns) and time.monotonic() - since < self.p['imu_wait_s']:
                return
            if not self.fusion.tracks_settled(g.stamp_ns, g.items):
                if time.monotonic() - since < self.p['tracks_wait_s']:
                    return
                self.tracks_timed_out += 1
            self.held.pop(0)
            t0 = time.thread_time()
            # Rig order, not arrival order: float sums must not depend on the scheduler.
            items = {n: g.items[n] for n in self.rig.names if n in g.items}
            fused = self.fusion.process(g.stamp_ns, items, wheel_twist=self.wheel.at(g.first_ns),
                                        wheel_stamp_ns=self.wheel.stamp_at(g.first_ns))
            ms = (time.thread_time() - t0) * 1e3
            if not (np.all(np.isfinite(fused.T_odom_base)) and is_valid_covariance(fused.pose_covariance)
                    and is_valid_covariance(fused.twist_covariance)):
                self.get_logger().error(f'fused estimate at {g.stamp_ns} is not finite/PD: not published')
                continue
            self.govern(g.stamp_ns)
            self.publish_map_scale()
            self.publish_road_normal(g.stamp_ns)
            self.publish_gyro_bias(g.stamp_ns)
            self.publish(fused, g, ms)
            if self.on_frame_done is not None:
                self.on_frame_done(self)

    def govern(self, stamp_ns):
        """A new frame schedule when the lag calls for one: published before the fused pose,
        so the quarters have it when they pick their next frame."""
        was_enabled = self.governor.enabled
        schedule = self.governor.update(stamp_ns, self.get_clock().now().nanoseconds,
                                        max(self.sync.last_stamp.values(), default=stamp_ns),
                                        self.frame_period_ns())
        if was_enabled and not self.governor.enabled:
            self.get_logger().warn(
                f'frame stamps and this node\'s clock differ by more than '
                f'{self.governor.clock_sanity_s:.0f} s: frames are never skipped (live, the '
                'driver must stamp with the system clock; a replay must publish /clock and '
                'run the general arbiter with use_sim_time)')
        if schedule is not None:
            self.issued.add(schedule)
            self.pub_schedule.publish(Int64MultiArray(data=schedule.to_list()))
            self.get_logger().info(
                f'behind the cameras: processing {schedule.keep} frame(s) in {schedule.stride}, '
                f'{self.governor.achieved_rate_hz():.1f} of {self.governor.camera_rate_hz():.1f} Hz, from '
                f'{schedule.from_ns / 1e9:.3f} s' if schedule.keep < schedule.stride else
                f'caught up: processing every frame from {schedule.from_ns / 1e9:.3f} s')

    def publish_road_normal(self, stamp_ns):
        """The road's normal at this frame, before its fused pose (the quarters use it from the
        next frame's on)."""
        up = self.fusion.road_normal(stamp_ns)
        if up is not None:
            msg = Vector3Stamped()
            msg.header.stamp = ns_to_stamp(stamp_ns)
            msg.header.frame_id = self.p['base_frame']
            msg.vector.x, msg.vector.y, msg.vector.z = (float(v) for v in up)
            self.pub_road_normal.publish(msg)

    def publish_gyro_bias(self, stamp_ns):
        """The gyro's bias as of this frame, before its fused pose (the quarters steer the
        next frame by it); NaN while the gyro is out (a bad IMU: they do not steer by it)."""
        if self.pub_gyro_bias is None:
            return
        bias = self.fusion.gyro_steer_bias()
        msg = Vector3Stamped()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.header.frame_id = self.p['base_frame']
        msg.vector.x, msg.vector.y, msg.vector.z = ((float('nan'),) * 3 if bias is None
                                                    else (float(v) for v in bias))
        self.pub_gyro_bias.publish(msg)

    def publish_map_scale(self):
        """A new map rescale, before the fused pose (it applies from the next frame on)."""
        command = self.fusion.map_scale_command
        if command is not None and command.epoch != self.map_scale_epoch:
            self.map_scale_epoch = command.epoch
            self.pub_map_scale.publish(Int64MultiArray(data=command.to_list()))
            self.get_logger().info(f'map rescaled by {command.factor:.4f} from '
                                   f'{command.from_ns / 1e9:.3f} s (scale source: rig rotation)')

    # --- hand-over between workers (coordinator) ------------------------------------------
    def idle(self) -> bool:
        return True

    def get_state(self):
        """Picklable state: the fusion core (pickled whole), wheel buffer, last fused stamp.
        /ego_motion/path restarts after a restore (its history is not carried)."""
        return {'fusion': self.fusion, 'wheel': self.wheel,
                'last_released_ns': self.sync.last_released_ns, 'sync_window_ns': self.sync.window_ns,
                'camera_periods_ns': dict(self.sync.period_ns),
                'window_learner': self.window_learner,
                'governor': self.governor.get_state(), 'issued': self.issued.get_state()}

    def set_state(self, s):
        self.fusion = s['fusion']
        self.wheel = s['wheel']
        self.sync.last_released_ns = s['last_released_ns']
        self.sync.window_ns = s.get('sync_window_ns', self.sync.window_ns)
        self.sync.period_ns.update(s.get('camera_periods_ns', {}))
        self.window_learner = s.get('window_learner', self.window_learner)
        self.governor.set_state(s['governor'])
        self.issued.set_state(s.get('issued'))

    def publish(self, fused, group, ms):
        stamp = ns_to_stamp(fused.stamp_ns)
        odom_frame, base_frame = self.p['odom_frame'], self.p['base_frame']
        # One feedback per distinct camera stamp (free-running cameras), oldest first: each
        # quarter triangulates from the fused pose at its own camera's capture time.
        for s in feedback_stamps(group, fused.stamp_ns):
            T, C = self.fusion.pose_at(fused, s)
            self.pub_fused.publish(estimate_to_msg(PoseEstimate(
                s, T, C, source='fused', state=fused.state), odom_frame))
        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = odom_frame
        odom.child_frame_id = base_frame
        fill_pose(odom.pose.pose, fused.T_odom_base)
        odom.pose.covariance = covariance_field(fused.odom_covariance if fused.odom_covariance is not None
                                                else fused.pose_covariance)
        t = odom.twist.twist
        t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z = (
            float(v) for v in fused.twist)
        odom.twist.covariance = covariance_field(fused.twist_covariance)
        # The status is built before /odom goes out and sent right after it: a crash between
        # the two (the frame saved, its status not) is then a window of two calls.
        missing = list(group.missing)
        level = 'ok' if fused.state == 'tracking' and not missing else 'warn'
        parts = [fused.state]
        if missing:
            parts.append(f'no estimate from cameras: {", ".join(missing)}')
        if fused.cameras_rejected:
            parts.append('rejected: ' + ', '.join(f'{k} ({v})' for k, v in fused.cameras_rejected.items()))
        imu = self.imu_status()
        imu_values = {}
        if imu is not None:
            imu_level, imu_message, imu_values = imu
            if imu_level != 'ok':
                parts.append(imu_message)
                level = 'error' if 'error' in (level, imu_level) else 'warn'
        status = diagnostics.status(
            'ego_motion/general_arbiter', level, '; '.join(parts),
            {**imu_values, 'state': fused.state, 'scale_observed': fused.scale_observed,
             'scale_source': fused.scale_fixed_by,
             'scale_relative_std': round(float(fused.scale_relative_std), 6),
             'scale_observations': self.fusion.scale.n_observations,
             'lone_track_rotations': self.fusion.lone_rotations,   # free-running cameras' own turns
             'tracks_timed_out': self.tracks_timed_out,
             'rig_fit': self.fusion.scale.fit_summary(),
             'cameras_used': ','.join(fused.cameras_used), 'cameras_missing': ','.join(missing),
             'frame_stride': self.governor.stride, 'frames_kept': f'{self.governor.keep}/{self.governor.stride}',
             'camera_rate_hz': round(self.governor.camera_rate_hz() or 0.0, 3),
             'achieved_rate_hz': round(self.governor.achieved_rate_hz() or 0.0, 3), 'arbiter_ms': ms,
             'estimates_off_schedule': self.off_schedule,
             'sync_timed_out': group.timed_out})
        if odom_due(self.last_odom_ns, fused.stamp_ns, self.p['odom_rate_hz']):
            self.last_odom_ns = fused.stamp_ns
            if self.p['publish_tf']:
                self.pub_tf.publish(TFMessage(transforms=[transform_msg(
                    fused.T_odom_base, odom_frame, base_frame, fused.stamp_ns)]))
            if self.path.add(fused.stamp_ns, fused.T_odom_base, PoseStamped(header=odom.header, pose=odom.pose.pose)):
                self.pub_path.publish(Path(header=odom.header, poses=[p[2] for p in self.path.poses]))
            self.pub_odom.publish(odom)
        diagnostics.emit(stamp, status, self.diag_sink, self.pub_diag)


def odom_due(last_ns, stamp_ns, rate_hz) -> bool:
    """Whether the state at stamp_ns goes out on /odom: every one at rate 0, else the first
    at least 1 / rate after the last published (stamps, not the wall clock: a replay gives
    the same /odom at any speed)."""
    if rate_hz <= 0 or last_ns is None:
        return True
    return stamp_ns - last_ns >= round(1e9 / rate_hz)


def feedback_stamps(group, fused_stamp_ns):
    """The stamps the fused pose is fed back at: every camera's own stamp in the group, in
    order (the fused stamp, the latest, last)."""
    return sorted(set(group.stamps.values()) | {fused_stamp_ns})


def main(args=None):
    return spin_node(GeneralArbiterNode, 'general_arbiter', args)
