"""The whole estimator in one process, no ROS transport: the same cores the nodes wrap,
called in the graph's order for every frame. It is the sequential baseline of the paper's
comparison (Ts) and a fast way to score a parameter change on a bag.

It gives the lockstep graph's /odom bit for bit: every estimate goes through the message
conversion it goes through in the graph (quarter -> camera arbiter -> general arbiter ->
fused-pose feedback; quaternions round the last bits), an image that comes before its
camera's first CameraInfo is processed once that arrives (the quarter node keeps it pending),
and the wheel twist is the one the general arbiter would pick. The estimator is chaotic (a
last-bit difference can move a final drift by 50 %), so anything less is another run.

Free-running cameras: images with identical stamps are one frame and every other image a
frame of its own, fused at its stamp, as the general arbiter groups them. With an opt-in
window (`sync_window_s` > 0, the general arbiter's parameter): images whose
stamps lie within the window are one frame, as the arbiter groups them; each camera is
processed at its own stamp, the frame fused at its latest, and the fused pose fed back at
every camera's stamp, oldest first, as the general arbiter publishes it.
"""
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Dict, List

from arbiter_node.general_fusion import GeneralFusion
from arbiter_node.quarter_fusion import PARAMETERS as QUARTER_FUSION_PARAMETERS, fuse_quarters
from arbiter_node.wheel_prior import WheelBuffer, twist_from_odometry
from camera_pose_nodes.camera_model import intrinsics_from_msg
from camera_pose_nodes.gyro_steer import GyroSteer
from camera_pose_nodes.image_conversion import image_msg_to_gray
from camera_pose_nodes.pose_estimate import PoseEstimate
from camera_pose_nodes.quarter_estimator import QuarterEstimator, QuarterParams
from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.ros_plumbing.imu_messages import imu_sample_from_cdr
from multicam_ego_motion.ros_plumbing.pose_messages import estimate_to_msg, msg_to_estimate, stamp_to_ns


@dataclass
class SequentialResult:
    fused: List[object] = field(default_factory=list)                  # FusedEstimate per frame
    cameras: Dict[str, list] = field(default_factory=lambda: defaultdict(list))
    quarters: Dict[str, list] = field(default_factory=lambda: defaultdict(list))
    frame_ms: List[float] = field(default_factory=list)
    # process CPU of each frame's estimation (quarters, fusion, feedback), not of reading the
    # bag: what a peer measured on images already in memory is compared with
    frame_cpu_ms: List[float] = field(default_factory=list)
    stage_ms: Dict[str, List[float]] = field(default_factory=lambda: defaultdict(list))
    imu_cpu_ms: float = 0.0      # process CPU of reading the IMU's samples (their bytes) into the fusion, all of them
    imu_samples: int = 0         # how many
    gyro_bias: List[object] = field(default_factory=list)   # the fusion's estimate per frame (None without a gyro)
    gyro_bias_fixes: int = 0     # of them measured from the tracks (general_fusion gyro_bias_from_tracks)
    lone_track_rotations: int = 0   # free-running cameras' rotations from their tracks (lone_camera_track_rotation)
    bearing_messages: int = 0    # the quarters' track messages a graph would send (bearings topics)
    bearing_points: int = 0      # ... and the tracks in them


def run_sequential(bag_path, rig, quarter_params: dict = None, fusion_params: dict = None,
                   use_wheel: bool = True, max_frames: int = None, progress=None,
                   quarters=(1, 2, 3, 4), sync_window_s: float = 0.0,
                   camera_fusion_params: dict = None) -> SequentialResult:
    """`quarters`: which quarters of every camera run (all four in the graph; fewer to show
    what one quarter alone achieves). `sync_window_s`: the general arbiter's frame window.
    `camera_fusion_params`: the camera arbiters' (quarter_fusion.PARAMETERS; their defaults
    where not given)."""
    window_ns = int(round(sync_window_s * 1e9))
    reader = Rosbag2Reader(bag_path)
    present = [c for c in rig.cameras if c.input_topic in reader.topics]
    if not present:
        raise UserError(f'bag {bag_path} has none of the rig\'s image topics '
                        f'({", ".join(c.input_topic for c in rig.cameras)})')
    qp = QuarterParams(**(quarter_params or {}))
    fusion = GeneralFusion(rig, fusion_params or {})
    cam_fusion = {k: v[0] for k, v in QUARTER_FUSION_PARAMETERS.items()}
    cam_fusion.update(camera_fusion_params or {})
    # as the quarter nodes publish them and the general arbiter subscribes
    sends_bearings = rig.sends_bearings and fusion.wants_bearings()
    topics = [c.input_topic for c in present] + [c.camera_info_topic for c in present
                                                  if c.camera_info_topic in reader.topics]
    wheel_topic = '/wheel/odom' if use_wheel and '/wheel/odom' in reader.topics else None
    if wheel_topic:
        topics.append(wheel_topic)
    imu_topic = rig.imu.topic if fusion.wants_imu() and rig.imu.topic in reader.topics else None
    if imu_topic:
        topics.append(imu_topic)
    # the quarters' own gyro (quarter nodes with use_imu), the general arbiter's bias after each frame
    steer = GyroSteer.for_rig(rig) if imu_topic and qp.gyro_steer else None
    by_topic = {c.input_topic: c for c in present}
    info_topic = {c.camera_info_topic: c for c in present}
    estimators = {}   # camera name -> [QuarterEstimator x4]
    intrinsics = {}   # camera name -> its first CameraInfo's intrinsics
    result = SequentialResult()
    frame = {}        # camera name -> image message of the current frame
    frame_stamps = {}  # camera name -> its image's stamp
    wheel = WheelBuffer()

    def as_received(est, source):
        # what a subscriber gets: the estimate through its ROS message
        return msg_to_estimate(estimate_to_msg(est), source=source)

    def add_new_bearings(name, q):
        # the features a quarter extracted after sending its frame's tracks (quarter_node)
        nb = q.new_bearings()
        if nb is not None:
            fusion.add_bearings(name, q.quarter, *nb)
            result.bearing_messages += 1
            result.bearing_points += len(nb[1])

    def flush():
        if not frame:
            return
        t0, c0 = time.perf_counter(), time.process_time()
        cams = {}
        common = max(frame_stamps.values())
        # Rig order, as the general arbiter fuses: float sums in another order differ in the
        # last bits, and gating decisions can amplify that over a run.
        for name, msg in sorted(frame.items(), key=lambda kv: rig.names.index(kv[0])):
            if name not in estimators:
                continue
            gray = image_msg_to_gray(msg, estimators[name][0].image_size, rig.camera(name).mono16_bits)
            ests = [q.process_image(frame_stamps[name], gray) for q in estimators[name]]
            if sends_bearings:
                # as the quarter nodes publish them; fused from the next frame on
                for q in estimators[name]:
                    add_new_bearings(name, q)
                    ids, xy, sigma = q.bearings()
                    fusion.add_bearings(name, q.quarter, frame_stamps[name], ids, xy, sigma)
                    result.bearing_messages += 1
                    result.bearing_points += len(ids)
            for e in ests:
                result.quarters[e.source].append(e)
                for k, v in e.stage_ms.items():
                    result.stage_ms[k].append(v)
            received = [as_received(e, e.source) for e in ests]
            cams[name] = as_received(fuse_quarters(received, source=name, **cam_fusion), name)
            result.cameras[name].append(cams[name])
        first = min(frame_stamps.values())
        fused = fusion.process(common, cams, wheel_twist=wheel.at(first), wheel_stamp_ns=wheel.stamp_at(first))
        if steer is not None:
            steer.set_bias(common, fusion.gyro_steer_bias())
        # (as the quarters get them: before the fused pose; the map scale latched, in time)
        road_up = fusion.road_normal(common)
        command = fusion.map_scale_command
        for qs in estimators.values():
            for q in qs:
                if road_up is not None:
                    q.add_road_normal(common, road_up)
                if command is not None:
                    q.rescale_command(command)
        partner_gray = {}
        for stamp in sorted(set(frame_stamps.values())):
            T, C = fusion.pose_at(fused, stamp)
            feedback = as_received(PoseEstimate(stamp, T, C, source='fused', state=fused.state), 'fused')
            for name, qs in estimators.items():
                # Stereo pairs: as a quarter node, once the partner's CameraInfo is known, the
                # fused pose is applied with the partner's image of the same stamp (the node
                # holds the fused pose until that image is there; absent from the bag: without)
                partners = rig.stereo_partners(name)
                partner = next((b for b in partners if b in intrinsics), None) if qp.stereo else None
                gray_b = None
                if partner is not None:
                    if not qs[0].wants_partner_image:
                        for q in qs:
                            q.set_partner(rig.camera(partner), intrinsics[partner])
                    if partner in frame and frame_stamps[partner] == stamp:
                        if partner not in partner_gray:
                            size = (intrinsics[partner].width, intrinsics[partner].height)
                            partner_gray[partner] = image_msg_to_gray(frame[partner], size,
                                                                      rig.camera(partner).mono16_bits)
                        gray_b = partner_gray[partner]
                for q in qs:
                    if q.takes_feedback(stamp):
                        q.apply_fused_pose(stamp, feedback.T_odom_base, feedback.covariance, gray_b)
                        if sends_bearings:
                            add_new_bearings(name, q)
        result.fused.append(fused)
        result.gyro_bias.append(fusion.ekf.gyro_bias)
        result.frame_ms.append((time.perf_counter() - t0) * 1e3)
        result.frame_cpu_ms.append((time.process_time() - c0) * 1e3)
        frame.clear()
        frame_stamps.clear()
        if progress:
            progress.update(1)

    def new_frame(name, stamp):
        if not frame_stamps:
            return False
        if window_ns == 0:
            return stamp != next(iter(frame_stamps.values()))
        lo, hi = min(frame_stamps.values()), max(frame_stamps.values())
        return name in frame or max(hi, stamp) - min(lo, stamp) > window_ns

    # the IMU's samples as the general arbiter takes them: bytes, read by wire_types
    for topic, msg, _ in reader.decoded(topics, raw_topics=(imu_topic,)):
        if topic == wheel_topic:
            wheel.add(stamp_to_ns(msg.header.stamp), *twist_from_odometry(msg))
            continue
        if topic == imu_topic:
            # (in log-time order: a frame is flushed when the next one's first image comes,
            # by when its gyro samples are in, as the general arbiter waits for them)
            c0 = time.process_time()
            try:
                sample = imu_sample_from_cdr(msg)
            except ValueError as e:
                raise UserError(f'bag {bag_path}: {imu_topic}: {e}') from None
            fusion.add_imu(sample.stamp_ns, sample.gyro, sample.gyro_covariance, sample.frame_id,
                           sample.accel, sample.accel_covariance)
            if steer is not None:
                steer.add(sample.stamp_ns, sample.frame_id, sample.gyro)
            result.imu_cpu_ms += (time.process_time() - c0) * 1e3
            result.imu_samples += 1
            continue
        if topic in info_topic:
            cam = info_topic[topic]
            if cam.name not in estimators:
                intr = intrinsics_from_msg(msg, cam.name)
                intrinsics[cam.name] = intr
                estimators[cam.name] = [QuarterEstimator(cam, q, intr, qp, (msg.width, msg.height), rig.floor_z,
                                                                rig.road_scale)
                                        for q in quarters]
                for q in estimators[cam.name]:
                    q.gyro = steer
            continue
        cam = by_topic[topic]
        stamp = stamp_to_ns(msg.header.stamp)
        if new_frame(cam.name, stamp):
            flush()
            if max_frames and len(result.fused) >= max_frames:
                break
        frame_stamps[cam.name] = stamp
        # Converted when the frame is complete: a camera's CameraInfo may follow its image
        # (the graph's quarter nodes hold such an image until the CameraInfo arrives).
        frame[cam.name] = msg
    if not (max_frames and len(result.fused) >= max_frames):
        flush()
    result.gyro_bias_fixes = fusion.bias_fixes
    result.lone_track_rotations = fusion.lone_rotations
    return result
