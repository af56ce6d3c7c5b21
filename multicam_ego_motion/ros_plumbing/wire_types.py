"""The ROS 2 Jazzy message types as rosbags builds, writes and reads them, for the topics that
come many times a frame: the quarters' track messages (one per quarter and frame) and the IMU's
samples (200 a second; read by cdr_stream, written here). Their subscriptions take the CDR bytes
(rclpy `raw=True`), their publishers send bytes rosbags wrote (or, for the track messages,
the same bytes put together by bearing_messages): rclpy's message objects (a
dozen Python objects a message, made and read field by field) cost 15 us a message, rosbags'
5-8. The bytes on the wire are the standard CDR encoding of the same type: any subscriber,
viewer or recorder takes them as usual. Generated bags (bag/rig_bag_writer) are written with the
same store: rosbags' bytes are the same for the same message, rclpy's padding is not."""
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)
TYPES = STORE.types


def from_cdr(data, typename: str):
    """The message of `typename` the CDR bytes hold; ValueError naming the type when they do
    not hold one (truncated, another type's)."""
    try:
        return STORE.deserialize_cdr(data, typename)
    except Exception as e:  # rosbags raises struct.error, IndexError, ... on bytes it cannot read
        raise ValueError(f'{len(data)} bytes that do not read as {typename} ({type(e).__name__}: {e})') from None


def to_cdr(msg, typename: str) -> bytes:
    return bytes(STORE.serialize_cdr(msg, typename))


def header(time_ns: int, frame_id: str):
    """A std_msgs/Header of this store at time_ns."""
    stamp = TYPES['builtin_interfaces/msg/Time'](sec=int(time_ns // 1_000_000_000),
                                                 nanosec=int(time_ns % 1_000_000_000))
    return TYPES['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id)
