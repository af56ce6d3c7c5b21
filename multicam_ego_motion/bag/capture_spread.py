"""The capture spread of a bag's cameras (arbiter_node/capture_spread.py) from the header
stamps of its first images: `replay` groups free-running cameras by the window it gives."""
from typing import List

from arbiter_node.capture_spread import CaptureSpread, capture_spread
from multicam_ego_motion.bag.header_stamp import header_stamp_ns

SAMPLE_S = 3.0          # image stamps read from the start of the bag


def bag_capture_spread(reader, image_topics: List[str], sample_s: float = SAMPLE_S) -> CaptureSpread:
    """capture_spread of the first `sample_s` seconds of the bag's images (header stamps read
    from the serialized messages: nothing is decoded)."""
    topics = [t for t in image_topics if t in reader.topics]
    stamps = {t: [] for t in topics}
    if not topics or reader.start_ns is None:
        return capture_spread(stamps)
    for m in reader.messages(topics, end_ns=reader.start_ns + int(sample_s * 1e9)):
        stamps[m.topic].append(header_stamp_ns(m.data))
    return capture_spread(stamps)
