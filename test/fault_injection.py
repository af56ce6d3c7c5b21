"""Build faulty bags for the fault-injection tests by transforming the committed default bag.

`rewrite_bag(dst, seconds, *edits)` copies the first `seconds` of bags/default through a
chain of edits and writes the result with the product's own Rosbag2Writer. An edit is a
function `list[Item] -> list[Item]`; the builders below return such functions. File-level
faults (a truncated or corrupted MCAP) are applied to a finished bag.

No ROS graph is involved: messages are decoded and re-serialized with rclpy's serializer.
"""
import copy
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer

REPO = Path(__file__).resolve().parents[1]
DEFAULT_BAG = REPO / 'bags' / 'default'
CAMERAS = ('front', 'left', 'back', 'right')
NS = 1_000_000_000


@dataclass
class Item:
    topic: str
    log_ns: int
    t: float          # seconds since the start of the source bag
    msg: object       # decoded message (edits replace it, never mutate the source's)


def load_items(seconds: float, src=DEFAULT_BAG):
    reader = Rosbag2Reader(src)
    end = reader.start_ns + round(seconds * NS)
    return [Item(topic, log_ns, (log_ns - reader.start_ns) / NS, msg)
            for topic, msg, log_ns in reader.decoded(end_ns=end)]


def rewrite_bag(dst, seconds: float, *edits, rig=True, chunk_size: int = 4 * 1024 * 1024):
    """Write the first `seconds` of the default bag, edited, to the new bag folder `dst`."""
    items = load_items(seconds)
    for edit in edits:
        items = list(edit(items))
    items.sort(key=lambda it: it.log_ns)   # stable: frame order within a log time is kept
    with Rosbag2Writer(dst, chunk_size=chunk_size) as w:
        for it in items:
            w.write(it.topic, it.msg, it.log_ns)
    if rig:
        shutil.copy(DEFAULT_BAG / 'rig.yaml', Path(dst) / 'rig.yaml')
    return Path(dst)


def _is_image(it, camera):
    return it.topic == f'/{camera}/image_raw'


def _replace_images(camera, change, t0=-math.inf, t1=math.inf):
    """Apply change(msg copy) to the camera's images with t0 <= t < t1."""
    def edit(items):
        for it in items:
            if _is_image(it, camera) and t0 <= it.t < t1:
                msg = copy.deepcopy(it.msg)
                change(msg)
                it = Item(it.topic, it.log_ns, it.t, msg)
            yield it
    return edit


def _pixels(msg):
    return np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.step)[:, :msg.width]


def _set_pixels(msg, gray, encoding='mono8', bytes_per_pixel=1):
    msg.height, msg.width = gray.shape[0], gray.shape[1] // bytes_per_pixel
    msg.encoding = encoding
    msg.step = gray.shape[1]
    msg.data = np.ascontiguousarray(gray).tobytes()


# ---- image faults ----------------------------------------------------------------------

def encoding(camera, name):
    """Re-encode the camera's mono8 images as 32FC1 or 16UC1 (encodings the graph does not
    read), pixel for pixel."""
    def change(msg):
        g = _pixels(msg)
        if name == '32FC1':
            _set_pixels(msg, g.astype('<f4').view(np.uint8), '32FC1', 4)
        elif name == '16UC1':
            _set_pixels(msg, (g.astype('<u2') * 256).view(np.uint8), '16UC1', 2)
        else:
            raise ValueError(name)
    return _replace_images(camera, change)


def resize(camera, width, height, t0=-math.inf, t1=math.inf):
    """Images of another size than the camera's CameraInfo says (between t0 and t1)."""
    return _replace_images(camera, lambda m: _set_pixels(
        m, cv2.resize(_pixels(m), (width, height), interpolation=cv2.INTER_AREA)), t0, t1)


def photometric(camera, kind, t0, t1):
    """All-black, saturated or heavily blurred frames between t0 and t1 (s)."""
    looks = {'black': lambda g: np.zeros_like(g),
             'saturated': lambda g: np.full_like(g, 255),
             'blurred': lambda g: cv2.GaussianBlur(g, (0, 0), sigmaX=12)}[kind]
    return _replace_images(camera, lambda m: _set_pixels(m, looks(_pixels(m))), t0, t1)


def drop_every(camera, n, t0=-math.inf, t1=math.inf):
    """The camera's driver drops every n-th frame (image and CameraInfo) between t0 and t1."""
    topics = {f'/{camera}/image_raw', f'/{camera}/camera_info'}

    def edit(items):
        frames = sorted({it.log_ns for it in items if it.topic in topics and t0 <= it.t < t1})
        dropped = set(frames[n - 1::n])
        return (it for it in items if not (it.topic in topics and it.log_ns in dropped))
    return edit


def stop_stream(camera, t0, t1):
    """The camera's driver stops (no image, no CameraInfo) between t0 and t1, then returns."""
    topics = {f'/{camera}/image_raw', f'/{camera}/camera_info'}
    return lambda items: (it for it in items if not (it.topic in topics and t0 <= it.t < t1))


def _camera_frames(items):
    """{log_ns: [items of camera topics]} in log order."""
    frames = {}
    for it in items:
        if it.topic.endswith(('/image_raw', '/camera_info')):
            frames.setdefault(it.log_ns, []).append(it)
    return frames


def duplicate_frame(index, delay_ns=1_000_000):
    """Every camera message of frame `index` delivered twice (same stamps), 1 ms apart."""
    def edit(items):
        log_ns = sorted(_camera_frames(items))[index]
        dups = [Item(it.topic, it.log_ns + delay_ns, it.t, it.msg)
                for it in items if it.log_ns == log_ns and it.topic.endswith(('/image_raw', '/camera_info'))]
        return list(items) + dups
    return edit


def swap_frames(index):
    """Frames `index` and `index + 1` arrive in swapped order: stamps go backwards once."""
    def edit(items):
        a, b = sorted(_camera_frames(items))[index:index + 2]
        out = []
        for it in items:
            if it.topic.endswith(('/image_raw', '/camera_info')) and it.log_ns in (a, b):
                it = Item(it.topic, b if it.log_ns == a else a, it.t, it.msg)
            out.append(it)
        return out
    return edit


# ---- calibration and bag-content faults ------------------------------------------------

def focal_length(camera, fx):
    """CameraInfo with another fx (NaN, 0, ...) in K and P."""
    def edit(items):
        for it in items:
            if it.topic == f'/{camera}/camera_info':
                msg = copy.deepcopy(it.msg)
                k, p = list(msg.k), list(msg.p)
                k[0], p[0] = fx, fx
                msg.k, msg.p = k, p
                it = Item(it.topic, it.log_ns, it.t, msg)
            yield it
    return edit


def drop_topic(topic):
    return lambda items: (it for it in items if it.topic != topic)


def replace_type(topic, make_msg):
    """Every message on `topic` replaced by make_msg(item) (another message type)."""
    return lambda items: (Item(it.topic, it.log_ns, it.t, make_msg(it)) if it.topic == topic
                          else it for it in items)


# ---- file-level faults -----------------------------------------------------------------

def mcap_file(bag) -> Path:
    return next(Path(bag).glob('*.mcap'))


def truncate(bag, fraction):
    """Cut the MCAP file as a killed writer would leave it: no summary, no footer."""
    f = mcap_file(bag)
    size = f.stat().st_size
    with open(f, 'r+b') as fh:
        fh.truncate(int(size * fraction))


def chunk_offsets(bag):
    """(start offset, length) of every chunk record, in file order."""
    from mcap.reader import make_reader
    with open(mcap_file(bag), 'rb') as fh:
        summary = make_reader(fh).get_summary()
    return sorted((c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes)


def corrupt_chunk(bag, index):
    """Overwrite the middle of chunk `index`'s compressed records with garbage; the summary
    (and so the bag's index) stays intact, as after a bad sector or a broken copy."""
    start, length = chunk_offsets(bag)[index]
    rng = np.random.default_rng(index)
    with open(mcap_file(bag), 'r+b') as fh:
        fh.seek(start + length // 2)
        fh.write(rng.integers(0, 256, size=min(4096, length // 4), dtype=np.uint8).tobytes())
