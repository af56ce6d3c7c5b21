"""Plain CDR (XCDR1, what ROS 2's rmw puts on the wire) read field by field, for a fixed-layout
message that comes hundreds of times a second: the IMU's (imu_messages, 200 a second), where
struct unpacks at the fields' offsets cost 4 us a message and the generic deserializer
(wire_types, rosbags) 17. (The quarters' track messages, of one fixed layout too, are put
together and read by bearing_messages itself.) Alignment is relative to the payload, after the 4-byte
encapsulation header; both byte orders are read."""
import struct
from typing import Tuple


class CdrReader:
    """A cursor over one serialized message; IndexError / struct.error / ValueError on bytes
    that end early or are not CDR (the callers name the type in their message)."""

    __slots__ = ('buf', 'pos', 'order')

    def __init__(self, data):
        buf = memoryview(data)
        if len(buf) < 4 or buf[0] != 0 or buf[1] not in (0, 1):
            raise ValueError('no CDR encapsulation header')
        self.buf, self.pos = buf, 4
        self.order = '<' if buf[1] == 1 else '>'

    def _align(self, size: int):
        self.pos += -(self.pos - 4) % size

    def unpack(self, fmt: str, align: int) -> Tuple:
        """The values of the struct format `fmt` (no byte-order prefix), its first field
        aligned to `align` bytes."""
        self._align(align)
        s = struct.Struct(self.order + fmt)
        out = s.unpack_from(self.buf, self.pos)
        self.pos += s.size
        return out

    def uint32(self) -> int:
        return self.unpack('I', 4)[0]

    def string(self) -> str:
        n = self.uint32()             # with its terminating NUL
        if n == 0 or self.pos + n > len(self.buf):
            raise ValueError(f'string of {n} bytes at {self.pos}')
        s = bytes(self.buf[self.pos:self.pos + n - 1]).decode()
        self.pos += n
        return s

    def stamp_and_frame(self) -> Tuple[int, str]:
        """std_msgs/Header: (stamp in ns, frame_id)."""
        sec, nanosec = self.unpack('iI', 4)
        return sec * 1_000_000_000 + nanosec, self.string()
