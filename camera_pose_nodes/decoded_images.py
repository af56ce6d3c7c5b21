"""Each camera image decoded once per process, not once per quarter.

A worker hosts up to four quarters of a camera (and the stereo partner's quarters take the
same image too): each used to convert the message to gray itself, four JPEG decodes of one
image. Here the gray image of (topic, stamp) is kept for the few newest frames of each
topic, read-only, and every quarter of the process gets the same array. A failed decode is
kept too, so each quarter reports the error without decoding again. ROS-free: the caller
passes the stamp.
"""
from collections import OrderedDict

import numpy as np

from camera_pose_nodes.image_conversion import check_size, image_msg_to_gray
from multicam_ego_motion.errors import UserError

# Frames kept per topic: two in flight in lockstep (a quarter prefetches k + 1 while others
# still process k), a stereo partner's image held for its fused pose, and some slack.
FRAMES_KEPT = 6


class DecodedImages:
    def __init__(self, frames_kept: int = FRAMES_KEPT):
        self.frames_kept = frames_kept
        self.by_topic = {}          # topic -> OrderedDict (stamp_ns, mono16_bits) -> gray or error
        self.decodes = 0            # how many messages were decoded (measured by the tests, bench)

    def gray(self, topic: str, stamp_ns: int, msg, expected_size=None,
             mono16_bits: int = 16) -> np.ndarray:
        """The gray image of `msg` (Image or CompressedImage) on `topic` at `stamp_ns`;
        UserError as image_conversion raises it, checked against `expected_size` each call."""
        frames = self.by_topic.setdefault(topic, OrderedDict())
        key = (int(stamp_ns), int(mono16_bits))
        found = frames.get(key)
        if found is None:
            self.decodes += 1
            try:
                found = image_msg_to_gray(msg, None, mono16_bits)
                found.flags.writeable = False       # shared by every quarter of the process
            except (UserError, ValueError) as e:
                found = UserError(str(e))
            frames[key] = found
            while len(frames) > self.frames_kept:
                frames.popitem(last=False)
        if isinstance(found, UserError):
            raise UserError(str(found))
        check_size(found.shape[1], found.shape[0], expected_size)
        return found


# The process's cache: a worker's quarters all use this one.
SHARED = DecodedImages()
