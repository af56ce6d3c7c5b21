"""Read header.stamp straight from a serialized (CDR) message, without decoding the rest.

The player needs the stamp of every camera image and of every acknowledgement; decoding a
whole image for eight bytes would cost more than publishing it. A message whose first field
is std_msgs/Header starts, after the 4-byte CDR encapsulation header, with int32 sec and
uint32 nanosec (both 4-byte aligned at offsets 0 and 4 of the CDR body).
"""
import struct
from functools import lru_cache

from multicam_ego_motion.bag.message_types import message_class

_CDR_LITTLE_ENDIAN = {0x01, 0x03}  # CDR_LE and PL_CDR_LE representation identifiers


@lru_cache(maxsize=None)
def has_header(typename: str) -> bool:
    """True when the type's first field is `std_msgs/Header header`."""
    fields = message_class(typename).get_fields_and_field_types()
    first = next(iter(fields.items()), None)
    return first == ('header', 'std_msgs/Header')


def header_stamp_ns(data: bytes):
    """header.stamp in nanoseconds of a serialized message that starts with a Header."""
    if len(data) < 12:
        raise ValueError('serialized message too short to hold a header')
    order = '<' if data[1] in _CDR_LITTLE_ENDIAN else '>'
    sec, nanosec = struct.unpack_from(order + 'iI', data, 4)
    return sec * 1_000_000_000 + nanosec
