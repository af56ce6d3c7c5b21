"""What fusing an IMU costs: CPU per frame of the estimation on the default bag's scene with a
200 Hz IMU, fused (`use_imu`) and not, interleaved on this machine (its speed drifts within
minutes: one pair of runs minutes apart compares two machines). The images and the wheel are
the default bag's, byte for byte (generate --imu-rate).

The estimation's CPU (the sequential pipeline's frame_cpu_ms: quarters, fusion, feedback), and
with the IMU also what a graph's general arbiter spends on its samples: reading each from its
bytes (wire_types, as its raw subscription takes them) into the fusion (ImuBuffer, ImuHealth:
the pipeline's imu_cpu_ms, which holds the quarters' GyroSteer too); each worker that hosts
quarters reading every sample's bytes for their steering, the gyro once and the stamp for each
other quarter of the worker (timed here per sample, times GRAPH_WORKERS); and the quarters' track messages, which a rig with an IMU sends
for the gyro's bias (written and read: timed here on a message of the run's mean size). Not
reading the bag: a robot's IMU comes over DDS.
"""
from dataclasses import dataclass
from pathlib import Path
from typing import List

from multicam_ego_motion.bench.accuracy_matrix import ensure_bag

IMU_RATE_HZ = 200.0
ROUNDS = 3
TARGET_PCT = 5.0        # issue: CPU per frame with the IMU at most 5 % more
GRAPH_WORKERS = 2       # worker processes hosting quarters, each reading the IMU once (2 cores)
QUARTERS_PER_CAMERA = 4


@dataclass
class ImuCost:
    without_ms: List[float]        # CPU ms per frame of each round, IMU not fused
    with_ms: List[float]           # ... fused

    @property
    def extra_pct(self) -> float:
        a, b = sum(self.without_ms) / len(self.without_ms), sum(self.with_ms) / len(self.with_ms)
        return 100.0 * (b - a) / a

    @property
    def met(self) -> bool:
        return self.extra_pct <= TARGET_PCT

    def lines(self) -> List[str]:
        a = ', '.join(f'{v:.1f}' for v in self.without_ms)
        b = ', '.join(f'{v:.1f}' for v in self.with_ms)
        return ['| IMU (200 Hz gyro, default bag\'s scene), estimation CPU per frame (with the IMU: its samples read into the fusion and by each worker\'s quarters, the quarters\' track messages) '
                '| without [ms] | with [ms] | more |', '|---|---|---|---:|',
                f'| {len(self.with_ms)} rounds, interleaved | {a} | {b} | {self.extra_pct:+.1f} % |']


def bearings_message_ms(points: int, repeats: int = 1000) -> float:
    """CPU ms to write one quarter's track message of `points` tracks and to read it (the
    bytes a quarter publishes and the general arbiter takes), fastest of 3."""
    import time

    import numpy as np

    from multicam_ego_motion.ros_plumbing.bearing_messages import bearings_from_cdr, bearings_to_cdr
    ids, xy, sigma = np.arange(points), np.zeros((points, 2)), np.full(points, 1e-3)
    best = float('inf')
    for _ in range(3):
        c0 = time.process_time()
        for _ in range(repeats):
            bearings_from_cdr(bearings_to_cdr(1, 'cam', ids, xy, sigma))
        best = min(best, (time.process_time() - c0) / repeats * 1e3)
    return best


def imu_reading_ms(quarters_per_worker: int, repeats: int = 2000) -> float:
    """CPU ms for one worker's quarters to read one sensor_msgs/Imu from its bytes (their raw
    subscription): the first to get it reads the gyro's sample into the shared GyroSteer, the
    others its stamp alone, which that steer has then (quarter_node.on_imu), fastest of 3."""
    import time

    import numpy as np
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu

    from camera_pose_nodes.gyro_steer import GyroSteer
    from multicam_ego_motion.ros_plumbing.imu_messages import imu_gyro_from_cdr, imu_stamp_from_cdr
    msg = Imu()
    msg.header.frame_id = 'imu_link'
    data = []
    for k in range(repeats):
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(1_000_000_000 + 5_000_000 * k, 1_000_000_000)
        data.append(serialize_message(msg))
    best = float('inf')
    for _ in range(3):
        steer = GyroSteer('imu_link', np.eye(3))
        c0 = time.process_time()
        for d in data:
            for _ in range(quarters_per_worker):
                stamp_ns = imu_stamp_from_cdr(d)
                if stamp_ns is None or steer.is_new(stamp_ns):
                    stamp_ns, frame_id, gyro = imu_gyro_from_cdr(d)
                    steer.add(stamp_ns, frame_id, gyro)
        best = min(best, (time.process_time() - c0) / repeats * 1e3)
    return best


def imu_cost(bags_folder: Path, params, rounds: int = ROUNDS) -> ImuCost:
    import cv2

    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import camera_fusion_params_from, fusion_params_from, quarter_params_from
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.sequential_pipeline import run_sequential

    # the default bag's scene (the matrix's loop, seed 7) with the IMU, generated on first use
    bag = ensure_bag(Path(bags_folder), 'loop', 7, IMU_RATE_HZ)
    rig, _ = resolve_rig(Rosbag2Reader(bag), None)
    qp, fp, cp = quarter_params_from(params), fusion_params_from(params), camera_fusion_params_from(params)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)                # as in a worker
    out = ImuCost([], [])
    try:
        for r in range(rounds):
            for use_imu, into in ((False, out.without_ms), (True, out.with_ms)):
                print(f'bench: IMU cost, round {r + 1} of {rounds}, {"with" if use_imu else "without"} ...',
                      flush=True)
                res = run_sequential(bag, rig, qp, dict(fp, use_imu=use_imu), camera_fusion_params=cp)
                n = max(len(res.fused), 1)
                messages_ms = 0.0
                if use_imu and qp.get('gyro_steer', True):
                    per_worker = -(-QUARTERS_PER_CAMERA * len(rig.cameras) // GRAPH_WORKERS)
                    messages_ms += res.imu_samples * GRAPH_WORKERS * imu_reading_ms(per_worker)
                if res.bearing_messages:
                    points = round(res.bearing_points / res.bearing_messages)
                    messages_ms += res.bearing_messages * bearings_message_ms(points)
                into.append((sum(res.frame_cpu_ms) + res.imu_cpu_ms + messages_ms) / n)
    finally:
        cv2.setNumThreads(threads)
    return out
