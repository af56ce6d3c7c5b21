"""What fusing an IMU costs: the sequential pipeline's estimation CPU per frame on the default
bag's scene with a 200 Hz IMU, fused (`use_imu`) and not, interleaved on this machine (its
speed drifts within minutes: one pair of runs minutes apart compares two machines). The
images and the wheel are the default bag's, byte for byte (generate --imu-rate). The CPU is
the whole run's over its frames: with the IMU fused that includes reading and taking in its
200 samples a second (deserialising them, ImuBuffer, ImuHealth), as the general arbiter's
IMU callback does in the graph; without, the same bag's IMU messages are not read.
"""
from dataclasses import dataclass
from pathlib import Path
from typing import List

from multicam_ego_motion.bench.accuracy_matrix import BAG_SETTINGS

IMU_RATE_HZ = 200.0
ROUNDS = 3
TARGET_PCT = 5.0        # issue: CPU per frame with the IMU at most 5 % more


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
        return ['| IMU (200 Hz gyro, default bag\'s scene), sequential pipeline CPU per frame '
                '| without [ms] | with [ms] | more |', '|---|---|---|---:|',
                f'| {len(self.with_ms)} rounds, interleaved | {a} | {b} | {self.extra_pct:+.1f} % |']


def imu_bag(folder: Path) -> Path:
    """The default bag's scene (loop, seed 7) with an IMU, generated on first use."""
    bag = folder / f'default_imu{IMU_RATE_HZ:g}'
    if not (bag / 'metadata.yaml').exists():
        from multicam_ego_motion.scenarios.generator import generate
        s = BAG_SETTINGS
        print(f'bench: generating {bag} ...', flush=True)
        generate('loop', str(bag), 7, s['duration'], s['rate'], s['width'], s['height'],
                 s['fx'], 0.0, 4, None, 'zstd', imu_rate=IMU_RATE_HZ)
    return bag


def imu_cost(bags_folder: Path, params, rounds: int = ROUNDS) -> ImuCost:
    import time

    import cv2

    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import fusion_params_from, quarter_params_from
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.sequential_pipeline import run_sequential

    bag = imu_bag(Path(bags_folder))
    rig, _ = resolve_rig(Rosbag2Reader(bag), None)
    qp, fp = quarter_params_from(params), fusion_params_from(params)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)                # as in a worker
    out = ImuCost([], [])
    try:
        for r in range(rounds):
            for use_imu, into in ((False, out.without_ms), (True, out.with_ms)):
                print(f'bench: IMU cost, round {r + 1} of {rounds}, {"with" if use_imu else "without"} ...',
                      flush=True)
                c0 = time.process_time()
                res = run_sequential(bag, rig, qp, dict(fp, use_imu=use_imu))
                into.append((time.process_time() - c0) / max(len(res.fused), 1) * 1e3)
    finally:
        cv2.setNumThreads(threads)
    return out
