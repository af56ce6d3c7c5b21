"""How fast the machine under a bench is, on fixed work of the pipeline's two kinds (ROS-free).

The bench's targets are CPU times per frame, and the machines it runs on differ: the same
commit measured 41.6 ms of sequential CPU per frame of the default bag on one 2-core VM and
105.7 ms on another. Two reference workloads that depend on nothing but the machine go beside
every bench, so that figures from different machines can be compared:

- Lucas-Kanade, the pipeline's largest single cost: OpenCV's pyramidal flow of 80 corners of
  a synthetic 160x120 quarter (the default bag's), 21x21 window, 3 levels, one thread;
- Python, the interpreter-bound rest (bookkeeping, small numpy calls): a fixed pure-Python
  loop.

Each is the fastest of several runs in CPU time of the calling thread, so other load on the
machine changes it little.
"""
import os
import platform
import time
from dataclasses import dataclass

import numpy as np

_LK_POINTS = 80
_LK_WINDOW = 21
_LK_LEVELS = 3
_PYTHON_LOOP = 300_000


@dataclass
class MachineSpeed:
    cpu: str
    cpus: int
    lk_us_per_point: float       # Lucas-Kanade, forward, CPU per tracked point [us]
    python_ms: float             # the reference Python loop [ms]

    def line(self) -> str:
        return (f'Machine: {self.cpu}, {self.cpus} CPUs; reference work (CPU time, fastest of '
                f'several runs): Lucas-Kanade {self.lk_us_per_point:.1f} us per point ({_LK_POINTS} '
                f'corners, {_LK_WINDOW}x{_LK_WINDOW} window, {_LK_LEVELS} levels, one thread), '
                f'Python loop {self.python_ms:.1f} ms. The '
                'bench\'s CPU figures scale with these: compare runs on different machines through '
                'them.')


def cpu_model() -> str:
    try:
        with open('/proc/cpuinfo') as f:
            for row in f:
                if row.lower().startswith('model name'):
                    return row.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or 'unknown CPU'


def _quarter_pair():
    """A textured 160x120 image and the same moved by (2.3, -1.6) px: fixed, seeded."""
    import cv2
    rng = np.random.default_rng(7)
    big = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.float32), (0, 0), 2.0)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    shift = np.float32([[1, 0, 2.3], [0, 1, -1.6]])
    moved = cv2.warpAffine(big, shift, (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return big[60:180, 80:240].copy(), moved[60:180, 80:240].copy()


def lk_us_per_point(repeats: int = 100) -> float:
    import cv2
    a, b = _quarter_pair()
    pts = cv2.goodFeaturesToTrack(a, _LK_POINTS, 0.01, 5)
    if pts is None or len(pts) == 0:
        raise RuntimeError('machine speed: the reference image gave no corners')
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        best = float('inf')
        for _ in range(repeats):
            t0 = time.thread_time()
            cv2.calcOpticalFlowPyrLK(a, b, pts, None, winSize=(_LK_WINDOW, _LK_WINDOW), maxLevel=_LK_LEVELS,
                                     criteria=crit)
            best = min(best, time.thread_time() - t0)
    finally:
        cv2.setNumThreads(threads)
    return best * 1e6 / len(pts)


def python_loop_ms(repeats: int = 5) -> float:
    best = float('inf')
    for _ in range(repeats):
        t0 = time.thread_time()
        acc = 0
        for i in range(_PYTHON_LOOP):
            acc += i * i % 7
        best = min(best, time.thread_time() - t0)
    return best * 1e3


def measure() -> MachineSpeed:
    return MachineSpeed(cpu_model(), os.cpu_count() or 1, lk_us_per_point(), python_loop_ms())
