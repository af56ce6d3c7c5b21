"""Read a rosbag2 bag with MCAP storage (a folder with metadata.yaml, or a bare .mcap file).

Every way a bag can be unreadable ends in a UserError that names the bag and the problem.
Two kinds are told apart (`scan_mcap`):

* unfinished: the file is MCAP from its start up to where it stops, but it has no footer (and
  so no summary): its writer was killed before closing it (SIGKILL, OOM, power cut), or the
  file was cut short. The message names `ego-motion reindex BAG`, which rebuilds it from its
  complete chunks.
* corrupt: anything else (no MCAP magic, an invalid record, data after the footer, a damaged
  summary or chunk).
"""
import struct
from dataclasses import dataclass
from pathlib import Path

import yaml
import zstandard
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message

from multicam_ego_motion.bag.message_types import message_class
from multicam_ego_motion.errors import UserError


@dataclass
class BagMessage:
    topic: str
    typename: str
    data: bytes
    log_time_ns: int

    def decode(self):
        return deserialize_message(self.data, message_class(self.typename))


def _mcap_files(path: Path):
    if not path.exists():
        raise UserError(f'bag not found: {path}')
    if path.is_file():
        if path.suffix != '.mcap':
            raise UserError(f'not an MCAP file: {path}')
        return [path]
    meta = path / 'metadata.yaml'
    if meta.exists():
        try:
            info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
            names = info.get('relative_file_paths') or [f['path'] for f in info['files']]
        except (yaml.YAMLError, KeyError, TypeError) as e:
            raise UserError(f'bag {path}: metadata.yaml is unreadable ({e})') from None
        if info.get('storage_identifier', 'mcap') != 'mcap':
            raise UserError(f'bag {path}: storage {info.get("storage_identifier")!r} '
                            'is not supported (only mcap)')
        files = [path / n for n in names]
        missing = [str(f) for f in files if not f.exists()]
        if missing:
            raise UserError(f'bag {path}: file listed in metadata.yaml is missing: {missing[0]}')
        return files
    files = sorted(path.glob('*.mcap'))
    if not files:
        raise UserError(f'bag {path}: no metadata.yaml and no .mcap file in the folder')
    return files


# A damaged chunk fails in its decompressor (zstandard.ZstdError; lz4 raises RuntimeError)
# or, with CRCs checked, in mcap itself (struct.error: a record shorter than its fields):
# all of them mean "this bag is damaged".
_CORRUPT = (McapError, ValueError, EOFError, OSError, KeyError, IndexError, MemoryError,
            zstandard.ZstdError, RuntimeError, struct.error)


MCAP_MAGIC = b'\x89MCAP0\r\n'
_OPCODES = {int(o) for o in Opcode}


@dataclass
class McapScan:
    """What the records of an .mcap file say about its state (no record is decoded)."""
    state: str            # 'complete' (ends with footer and magic), 'unfinished', 'corrupt'
    valid_end: int        # byte offset after the last whole, valid record
    records: int          # whole, valid records (the header included)
    reason: str           # for unfinished and corrupt: where and how the file stops


def scan_mcap(path) -> McapScan:
    """Walk the record headers (opcode, length) of an .mcap file from its start: cheap (9
    bytes read per record), and enough to tell an unfinished file from a corrupt one."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, 'rb') as fh:
        magic = fh.read(len(MCAP_MAGIC))
        if magic != MCAP_MAGIC:
            if MCAP_MAGIC.startswith(magic):
                return McapScan('unfinished', 0, 0, f'it ends after {size} bytes, inside the MCAP magic')
            return McapScan('corrupt', 0, 0, 'it does not start with the MCAP magic')
        offset, records = len(MCAP_MAGIC), 0
        while True:
            fh.seek(offset)
            head = fh.read(9)
            if not head:
                return McapScan('unfinished', offset, records,
                                f'it ends after {records} whole records (byte {offset}), without a footer')
            if len(head) < 9:
                return McapScan('unfinished', offset, records,
                                f'it ends inside a record header at byte {offset}, without a footer')
            opcode, length = struct.unpack('<BQ', head)
            if opcode not in _OPCODES or (records == 0 and opcode != Opcode.HEADER):
                return McapScan('corrupt', offset, records,
                                f'invalid record (opcode 0x{opcode:02x}) at byte {offset}')
            end = offset + 9 + length
            if end > size:
                return McapScan('unfinished', offset, records,
                                f'it ends inside a {Opcode(opcode).name.lower()} record at byte '
                                f'{offset} ({size - offset} of its {9 + length} bytes), without a footer')
            records += 1
            if opcode == Opcode.FOOTER:
                fh.seek(end)
                tail = fh.read(len(MCAP_MAGIC) + 1)
                if tail == MCAP_MAGIC:
                    return McapScan('complete', end, records, '')
                if len(tail) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(tail):
                    return McapScan('unfinished', end, records, 'it ends inside its closing MCAP magic')
                return McapScan('corrupt', end, records, f'unexpected bytes after the footer (byte {end})')
            offset = end


def unfinished_error(bag, f, reason):
    return UserError(f'bag {f} is unfinished: {reason} (its writer was stopped before closing it, '
                     f'or the file was cut short); `ego-motion reindex {bag}` rebuilds it from its '
                     'complete chunks')


def _unreadable(bag, f, e=None):
    """The error for a file whose summary cannot be read: unfinished or corrupt."""
    try:
        scan = scan_mcap(f)
    except OSError as oe:
        return UserError(f'bag {f} cannot be read ({oe})')
    if scan.state == 'unfinished':
        return unfinished_error(bag, f, scan.reason)
    if e is None:   # complete, with a footer, but written without a summary
        return UserError(f'bag {f} has no MCAP summary (index); `ego-motion reindex {bag}` builds one')
    return _corrupt(f, e, scan.reason if scan.state == 'corrupt' else '')


def _corrupt(path, e, where=''):
    what = type(e).__name__
    detail = f'{what}: {e}'.rstrip().rstrip(':')
    return UserError(f'bag {path} is corrupt ({where + "; " if where else ""}{detail})')


class Rosbag2Reader:
    """Topics, types and messages of a bag, in log-time order."""

    def __init__(self, path):
        self.path = Path(path)
        self.files = _mcap_files(self.path)
        self.topics = {}   # name -> typename
        self.counts = {}   # name -> message count
        self.start_ns = None  # log time of the first and last message (None: empty bag)
        self.end_ns = None
        for f in self.files:
            try:
                with open(f, 'rb') as stream:
                    summary = make_reader(stream).get_summary()
            except _CORRUPT as e:
                raise _unreadable(self.path, f, e) from None
            if summary is None:
                raise _unreadable(self.path, f)
            for cid, ch in summary.channels.items():
                schema = summary.schemas.get(ch.schema_id)
                self.topics[ch.topic] = schema.name if schema else ''
                n = summary.statistics.channel_message_counts.get(cid, 0) if summary.statistics else 0
                self.counts[ch.topic] = self.counts.get(ch.topic, 0) + n
            stats = summary.statistics
            if stats is not None and stats.message_count:
                self.start_ns = min(self.start_ns or stats.message_start_time,
                                    stats.message_start_time)
                self.end_ns = max(self.end_ns or 0, stats.message_end_time)

    def require(self, topics):
        """Raise a UserError naming every requested topic the bag does not hold."""
        missing = [t for t in topics if t not in self.topics]
        if missing:
            raise UserError(f'bag {self.path} has no topic {", ".join(missing)} '
                            f'(it has: {", ".join(sorted(self.topics)) or "none"})')

    def messages(self, topics=None, start_ns=None, end_ns=None):
        """Yield BagMessage in log-time order; corrupt data raises UserError."""
        if topics is not None:
            self.require(topics)
        for f in self.files:
            try:
                with open(f, 'rb') as stream:
                    # CRCs on: an uncompressed chunk with flipped bytes must not decode as data.
                    reader = make_reader(stream, validate_crcs=True)
                    for schema, channel, msg in reader.iter_messages(
                            topics=list(topics) if topics is not None else None,
                            starting_at=start_ns, ending_before=end_ns, log_time_order=True):
                        yield BagMessage(channel.topic, schema.name if schema else '',
                                         msg.data, msg.log_time)
            except _CORRUPT as e:
                raise _corrupt(f, e) from None

    def decoded(self, topics=None, raw_topics=(), **kw):
        """Yield (topic, message, log_time_ns) with messages deserialized by rclpy; those of
        `raw_topics` as their CDR bytes (as a raw subscription takes them)."""
        for m in self.messages(topics, **kw):
            if m.topic in raw_topics:
                yield m.topic, bytes(m.data), m.log_time_ns
                continue
            try:
                yield m.topic, m.decode(), m.log_time_ns
            except Exception as e:  # rclpy raises plain RuntimeError/TypeError on bad CDR
                raise UserError(f'bag {self.path}: message on {m.topic} does not decode as '
                                f'{m.typename} ({e})') from None
