"""Write a rosbag2 bag with MCAP storage: a folder with metadata.yaml and one .mcap file.

Messages are serialized to CDR by rclpy (the rmw's own serializer), so what lands in the bag
is byte-for-byte what a ROS 2 subscriber receives.
"""
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import yaml
from mcap.writer import CompressionType, Writer
from rclpy.serialization import serialize_message

from multicam_ego_motion import interrupt
from multicam_ego_motion.bag.message_types import message_definition, typename_of
from multicam_ego_motion.errors import UserError

# libyaml's emitter when PyYAML has it (same text for this plain document): the recorder
# rewrites metadata.yaml every second, and the pure-Python one took ~12 ms of the replay
# process's CPU for a 25-topic bag.
_SAFE_DUMPER = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


@dataclass
class FileStats:
    """What metadata.yaml says about one .mcap file of a bag."""
    path: str                                    # relative to the bag folder
    topics: Dict[str, Tuple[str, int]]           # name -> (type, message count)
    first_ns: Optional[int] = None               # log time of the first and last message
    last_ns: Optional[int] = None


def write_metadata(folder, files: List[FileStats]):
    """Write (atomically: a reader never sees half of it) the rosbag2 metadata.yaml of a bag
    made of `files`, in the format rosbag2 itself writes (version 8, storage mcap)."""
    folder = Path(folder)

    def span(first, last):
        return (first or 0), ((last - first) if first is not None else 0)

    firsts = [f.first_ns for f in files if f.first_ns is not None]
    lasts = [f.last_ns for f in files if f.last_ns is not None]
    start, duration = span(min(firsts) if firsts else None, max(lasts) if lasts else None)
    topics = {}
    for f in files:
        for name, (typ, count) in f.topics.items():
            topics.setdefault(name, [typ, 0])[1] += count
    info = {'rosbag2_bagfile_information': {
        'version': 8,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': sum(c for _, c in topics.values()),
        'topics_with_message_count': [{
            'topic_metadata': {'name': name, 'type': typ, 'serialization_format': 'cdr',
                               'offered_qos_profiles': '', 'type_description_hash': ''},
            'message_count': count} for name, (typ, count) in topics.items()],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.path for f in files],
        'files': [{'path': f.path,
                   'starting_time': {'nanoseconds_since_epoch': span(f.first_ns, f.last_ns)[0]},
                   'duration': {'nanoseconds': span(f.first_ns, f.last_ns)[1]},
                   'message_count': sum(c for _, c in f.topics.values())} for f in files],
        'custom_data': {},
        'ros_distro': 'jazzy',
    }}
    tmp = folder / 'metadata.yaml.tmp'
    with open(tmp, 'w') as fh:
        yaml.dump(info, fh, Dumper=_SAFE_DUMPER, sort_keys=False)
    os.replace(tmp, folder / 'metadata.yaml')


class Rosbag2Writer:
    """Append messages to a new bag; `close()` (or the context manager) writes metadata.yaml."""

    def __init__(self, path, compression: str = 'zstd', chunk_size: int = 4 * 1024 * 1024):
        self.path = Path(path)
        if self.path.exists() and any(self.path.iterdir()):
            raise UserError(f'output bag folder {self.path} exists and is not empty')
        self.path.mkdir(parents=True, exist_ok=True)
        self.file_name = f'{self.path.name}_0.mcap'
        self._stream = open(self.path / self.file_name, 'wb')
        comp = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4,
                'none': CompressionType.NONE}[compression]
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile='ros2', library='multicam_ego_motion')
        self._schemas = {}
        self._channels = {}
        self._topics = {}  # name -> [type, count]
        self._first = None
        self._last = None
        self._closed = False

    def add_topic(self, topic: str, typename: str):
        if topic in self._channels:
            return self._channels[topic]
        if typename not in self._schemas:
            self._schemas[typename] = self._writer.register_schema(
                name=typename, encoding='ros2msg',
                data=message_definition(typename).encode())
        self._channels[topic] = self._writer.register_channel(
            topic=topic, message_encoding='cdr', schema_id=self._schemas[typename],
            metadata={'offered_qos_profiles': ''})
        self._topics[topic] = [typename, 0]
        return self._channels[topic]

    def write(self, topic: str, msg, time_ns: int):
        """Serialize and append `msg`; `time_ns` is the receive (log) time."""
        self.write_serialized(topic, typename_of(msg), serialize_message(msg), time_ns)

    def write_serialized(self, topic: str, typename: str, data: bytes, time_ns: int):
        channel = self.add_topic(topic, typename)
        time_ns = int(time_ns)
        self._writer.add_message(channel_id=channel, log_time=time_ns, publish_time=time_ns,
                                 data=data, sequence=self._topics[topic][1])
        self._topics[topic][1] += 1
        self._first = time_ns if self._first is None else min(self._first, time_ns)
        self._last = time_ns if self._last is None else max(self._last, time_ns)

    def message_counts(self):
        return {t: c for t, (_, c) in self._topics.items()}

    def flush(self):
        """Push buffered messages to the OS as a finished chunk and refresh metadata.yaml.

        A process killed after this (SIGKILL) leaves a .mcap without summary/footer whose
        chunks up to here are intact: `ego-motion reindex BAG` rebuilds a complete bag from
        them (readers call it unfinished until then).
        """
        if self._closed:
            return
        self._writer.flush()
        self.write_metadata()

    def close(self):
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._stream.flush()
        os.fsync(self._stream.fileno())
        self._stream.close()
        self.write_metadata()
        if interrupt.requested():   # closed on the way out after a signal: say it was kept
            interrupt.note(kept=f'kept {self.path}: {sum(self.message_counts().values())} messages, '
                                'closed with its summary and metadata.yaml')

    def write_metadata(self):
        write_metadata(self.path, [FileStats(self.file_name, {t: (typ, n) for t, (typ, n) in self._topics.items()},
                                             self._first, self._last)])

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
