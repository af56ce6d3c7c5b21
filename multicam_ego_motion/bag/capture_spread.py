"""The capture spread of a bag's cameras (arbiter_node/capture_spread.py) from the header
stamps of its first images: `replay` groups free-running cameras by the window it gives."""
from typing import List

from arbiter_node.capture_spread import CaptureSpread, capture_spread
from multicam_ego_motion.bag.header_stamp import header_stamp_ns
from multicam_ego_motion.errors import UserError

SAMPLE_S = 3.0          # image stamps read from the start of the bag


def bag_capture_spread(reader, image_topics: List[str], sample_s: float = SAMPLE_S) -> CaptureSpread:
    """capture_spread of the first `sample_s` seconds of the bag's images (header stamps read
    from the serialized messages: nothing is decoded)."""
    topics = [t for t in image_topics if t in reader.topics]
    stamps = {t: [] for t in topics}
    if not topics or reader.start_ns is None:
        return capture_spread(stamps)
    try:
        for m in reader.messages(topics, end_ns=reader.start_ns + int(sample_s * 1e9)):
            try:
                stamps[m.topic].append(header_stamp_ns(m.data))
            except ValueError:
                continue    # not an image with a header: the replay's type check names it
    except UserError:
        pass        # damaged data: the player names it where it plays it, after what comes before
    return capture_spread(stamps)
