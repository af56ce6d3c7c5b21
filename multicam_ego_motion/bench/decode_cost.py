"""What each image input costs to turn into the tracker's gray image, per 640x480 image
(ROS-free): the same textured colour scene as each encoding a camera driver writes, through
the graph's own conversion (camera_pose_nodes/image_conversion). CPU time of the calling
thread, OpenCV on one thread as in a worker, fastest of several runs. A worker decodes each
image once for all its quarters of that camera (decoded_images), so this is a cost per
image and worker, not per quarter.
"""
import time
from types import SimpleNamespace

import numpy as np

WIDTH, HEIGHT = 640, 480
REPEATS = 20


def scene():
    """A seeded, smooth colour image with the texture of the generated scenes."""
    import cv2
    rng = np.random.default_rng(11)
    small = rng.integers(0, 256, (HEIGHT // 8, WIDTH // 8, 3), dtype=np.uint8)
    big = cv2.resize(small, (WIDTH, HEIGHT), interpolation=cv2.INTER_CUBIC)
    noise = rng.normal(0, 6, big.shape)
    return np.clip(big + noise, 0, 255).astype(np.uint8)


def inputs():
    """(name, message as a driver writes it) for each input kind (duck-typed messages)."""
    import cv2
    bgr = scene()
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)

    def raw(encoding, pixels, step):
        return SimpleNamespace(encoding=encoding, height=HEIGHT, width=WIDTH, step=step,
                               is_bigendian=0, data=np.ascontiguousarray(pixels).tobytes())

    def compressed(fmt, ext, img, params=()):
        return SimpleNamespace(format=fmt, data=cv2.imencode(ext, img, list(params))[1].tobytes())
    bayer = np.zeros((HEIGHT, WIDTH), np.uint8)          # rggb: R at (0, 0)
    bayer[0::2, 0::2], bayer[0::2, 1::2] = bgr[0::2, 0::2, 2], bgr[0::2, 1::2, 1]
    bayer[1::2, 0::2], bayer[1::2, 1::2] = bgr[1::2, 0::2, 1], bgr[1::2, 1::2, 0]
    yuv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV)
    uyvy = np.stack([yuv[:, 0::2, 1], yuv[:, 0::2, 0], yuv[:, 0::2, 2], yuv[:, 1::2, 0]], -1)
    q90 = (cv2.IMWRITE_JPEG_QUALITY, 90)
    return [
        ('mono8 (reference)', raw('mono8', gray, WIDTH)),
        ('bgr8', raw('bgr8', bgr, 3 * WIDTH)),
        ('bayer_rggb8', raw('bayer_rggb8', bayer, WIDTH)),
        ('yuv422 (uyvy)', raw('yuv422', uyvy, 2 * WIDTH)),
        ('mono16', raw('mono16', gray.astype('<u2') * 257, 2 * WIDTH)),
        ('JPEG q90, mono8', compressed('mono8; jpeg compressed mono8', '.jpg', gray, q90)),
        ('JPEG q90, bgr8', compressed('bgr8; jpeg compressed bgr8', '.jpg', bgr, q90)),
        ('PNG, mono8', compressed('mono8; png compressed mono8', '.png', gray)),
        ('PNG, bgr8', compressed('bgr8; png compressed bgr8', '.png', bgr)),
    ]


def measure(repeats: int = REPEATS):
    """[(name, bytes per image, CPU ms per image)]."""
    import cv2

    from camera_pose_nodes.image_conversion import image_msg_to_gray
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    rows = []
    try:
        for name, msg in inputs():
            best = float('inf')
            for _ in range(repeats):
                t0 = time.thread_time()
                image_msg_to_gray(msg, (WIDTH, HEIGHT))
                best = min(best, time.thread_time() - t0)
            rows.append((name, len(msg.data), best * 1e3))
    finally:
        cv2.setNumThreads(threads)
    return rows


def lines(rows=None):
    rows = measure() if rows is None else rows
    out = [f'| decode to gray, per {WIDTH}x{HEIGHT} image (once per worker and camera) | '
           'bytes | CPU [ms] |', '|---|---:|---:|']
    out += [f'| {name} | {size} | {ms:.2f} |' for name, size, ms in rows]
    return out
