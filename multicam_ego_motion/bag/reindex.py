"""`ego-motion reindex BAG`: rebuild a bag whose writer never closed it, as `ros2 bag reindex`
does.

A writer killed with SIGKILL (or by the OOM killer, or a power cut) leaves an .mcap without
its summary and footer: standard readers refuse it ("File end magic is invalid"), ours call it
unfinished. Its complete chunks are intact (the recorder finishes a chunk every second). This
reads every whole record from the start of each such file with mcap's StreamReader (the
chunks' CRCs checked; a damaged chunk is skipped and counted), writes them into a new,
complete file of the same name (summary, statistics, indexes) and rewrites metadata.yaml from
the files' summaries. The original file is kept beside it as NAME.mcap.unfinished. Files that
are complete are left as they are (their counts go into metadata.yaml).

BAG is a bag folder (metadata.yaml and .mcap files) or a bare .mcap file (no metadata.yaml
then). What was written after the last complete chunk (at most the last second of a
recording) is lost: it never reached the file.
"""
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import yaml
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from multicam_ego_motion.bag.rosbag2_reader import _CORRUPT, MCAP_MAGIC, scan_mcap
from multicam_ego_motion.bag.rosbag2_writer import FileStats, write_metadata
from multicam_ego_motion.errors import UserError

KEPT_SUFFIX = '.unfinished'
LIBRARY = 'multicam_ego_motion reindex'


@dataclass
class FileResult:
    path: Path
    rebuilt: bool                       # False: the file was complete, left as it was
    stats: FileStats
    kept_as: Optional[Path] = None      # the original, when rebuilt
    reason: str = ''                    # how the original ended
    chunks: int = 0                     # complete chunks read
    damaged_chunks: int = 0             # complete, but failing their CRC / decompression
    orphans: int = 0                    # messages whose channel record was in a damaged chunk

    @property
    def messages(self) -> int:
        return sum(n for _, n in self.stats.topics.values())


@dataclass
class ReindexResult:
    bag: Path
    files: List[FileResult] = field(default_factory=list)
    metadata: Optional[Path] = None     # metadata.yaml written (None for a bare .mcap)

    @property
    def messages(self) -> int:
        return sum(f.messages for f in self.files)

    @property
    def recovered(self) -> int:
        return sum(f.messages for f in self.files if f.rebuilt)


class _Prefix:
    """The first `size` bytes of a binary file, as a stream (StreamReader reads `read(n)`)."""

    def __init__(self, fh, size: int):
        self._fh, self._left = fh, size

    def read(self, n: int = -1) -> bytes:
        n = self._left if n is None or n < 0 else min(n, self._left)
        data = self._fh.read(n)
        self._left -= len(data)
        return data


def _summary_stats(path: Path, summary) -> FileStats:
    topics = {}
    stats = summary.statistics
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        n = stats.channel_message_counts.get(cid, 0) if stats else 0
        typ, m = topics.get(ch.topic, (schema.name if schema else '', 0))
        topics[ch.topic] = (typ, m + n)
    if stats is not None and stats.message_count:
        return FileStats(path.name, topics, stats.message_start_time, stats.message_end_time)
    return FileStats(path.name, topics)


def read_summary(path: Path):
    """The file's summary, or None when it has none (unfinished, or written without)."""
    try:
        with open(path, 'rb') as fh:
            return make_reader(fh).get_summary()
    except _CORRUPT:
        return None


def _records(src: Path, valid_end: int, result: 'FileResult'):
    """The whole records of src up to valid_end, chunks broken up (their CRCs checked: a
    damaged chunk is skipped and counted)."""
    with open(src, 'rb') as fh:
        if valid_end <= len(MCAP_MAGIC):
            return
        it = StreamReader(_Prefix(fh, valid_end), emit_chunks=True, record_size_limit=None).records
        while True:
            try:
                record = next(it)
            except (StopIteration, EndOfFile):     # EndOfFile: after the last whole record
                return
            except _CORRUPT as e:      # a whole record that does not parse
                result.reason += f'; stopped at a damaged record ({type(e).__name__}: {e})'
                return
            if isinstance(record, Chunk):
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                except _CORRUPT:
                    result.damaged_chunks += 1
                    continue
                result.chunks += 1
                yield from inner
            else:
                yield record


def rebuild(src: Path, dst: Path, chunk_size: int = 4 * 1024 * 1024) -> FileResult:
    """Write every message of src's complete chunks into the new file dst (complete: summary,
    indexes, statistics; zstd chunks like the recorder's). src is only read."""
    scan = scan_mcap(src)
    if scan.state == 'corrupt' and scan.valid_end == 0:
        raise UserError(f'{src} is not an MCAP file ({scan.reason}): nothing to reindex')
    result = FileResult(dst, True, FileStats(dst.name, {}), reason=scan.reason)
    schemas: Dict[int, Schema] = {}
    channels: Dict[int, Channel] = {}
    schema_ids, channel_ids = {}, {}
    topics = {}            # topic -> [type, count]
    first = last = None
    with open(dst, 'wb') as out:
        writer = None
        for r in _records(src, scan.valid_end, result):
            if writer is None:
                writer = Writer(out, chunk_size=chunk_size, compression=CompressionType.ZSTD)
                header = r if isinstance(r, Header) else None
                writer.start(profile=header.profile if header else 'ros2',
                             library=header.library if header else LIBRARY)
            if isinstance(r, Schema):
                if r.id not in schema_ids:
                    schemas[r.id] = r
                    schema_ids[r.id] = writer.register_schema(r.name, r.encoding, r.data)
            elif isinstance(r, Channel):
                if r.id not in channel_ids:
                    channels[r.id] = r
                    channel_ids[r.id] = writer.register_channel(
                        r.topic, r.message_encoding, schema_ids.get(r.schema_id, 0), r.metadata)
                    schema = schemas.get(r.schema_id)
                    topics.setdefault(r.topic, [schema.name if schema else '', 0])
            elif isinstance(r, Message):
                cid = channel_ids.get(r.channel_id)
                if cid is None:
                    result.orphans += 1
                    continue
                writer.add_message(cid, r.log_time, r.data, r.publish_time, r.sequence)
                topics[channels[r.channel_id].topic][1] += 1
                first = r.log_time if first is None else min(first, r.log_time)
                last = r.log_time if last is None else max(last, r.log_time)
            elif isinstance(r, Metadata):
                writer.add_metadata(r.name, r.metadata)
            elif isinstance(r, Attachment):
                writer.add_attachment(r.create_time, r.log_time, r.name, r.media_type, r.data)
        if writer is None:            # not even a whole header: an empty, complete file
            writer = Writer(out, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            writer.start(profile='ros2', library=LIBRARY)
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    result.stats = FileStats(dst.name, {t: (typ, n) for t, (typ, n) in topics.items()}, first, last)
    return result


def _bag_files(bag: Path) -> List[Path]:
    meta = bag / 'metadata.yaml'
    names = []
    if meta.exists():
        try:
            info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
            names = info.get('relative_file_paths') or [f['path'] for f in info['files']]
        except (yaml.YAMLError, KeyError, TypeError):
            names = []           # rebuilt from the files themselves
    files = [bag / n for n in names if (bag / n).exists()]
    listed = set(files)
    files += [f for f in sorted(bag.glob('*.mcap')) if f not in listed]
    if not files:
        raise UserError(f'bag {bag}: no .mcap file to reindex')
    return files


def reindex_file(path: Path) -> FileResult:
    summary = read_summary(path)
    if summary is not None:
        return FileResult(path, False, _summary_stats(path, summary))
    kept = path.with_name(path.name + KEPT_SUFFIX)
    if kept.exists():
        raise UserError(f'{kept} exists (an earlier reindex?): move it away first, '
                        f'it is the original of {path}')
    tmp = path.with_name(path.name + '.reindexing')
    try:
        result = rebuild(path, tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    from multicam_ego_motion import interrupt
    with interrupt.deferred():  # never the original moved away without the rebuilt file in place
        os.replace(path, kept)  # the original stays, beside the rebuilt file
        os.replace(tmp, path)
    result.path, result.kept_as = path, kept
    result.stats.path = path.name
    return result


def reindex(bag) -> ReindexResult:
    bag = Path(bag)
    if not bag.exists():
        raise UserError(f'bag not found: {bag}')
    if bag.is_file():
        if bag.suffix != '.mcap':
            raise UserError(f'not an MCAP file: {bag}')
        return ReindexResult(bag, [reindex_file(bag)])
    result = ReindexResult(bag, [reindex_file(f) for f in _bag_files(bag)])
    write_metadata(bag, [f.stats for f in result.files])
    result.metadata = bag / 'metadata.yaml'
    return result


# ---- command line ---------------------------------------------------------------------

def configure_parser(parser):
    parser.add_argument('bag', help='bag folder (metadata.yaml + .mcap) or .mcap file')


def describe(r: ReindexResult) -> List[str]:
    lines = []
    for f in r.files:
        if not f.rebuilt:
            lines.append(f'reindex: {f.path} is complete ({f.messages} messages): left as it is')
            continue
        lost = []
        if f.damaged_chunks:
            lost.append(f'{f.damaged_chunks} damaged chunk(s) skipped')
        if f.orphans:
            lost.append(f'{f.orphans} message(s) of channels lost with them')
        per_topic = ', '.join(f'{t} {n}' for t, (_, n) in sorted(f.stats.topics.items()) if n)
        lines.append(f'reindex: {f.path} was unfinished ({f.reason or "no summary"}): recovered {f.messages} '
                     f'messages from {f.chunks} complete chunks'
                     + (f' ({per_topic})' if per_topic else '')
                     + (f'; {"; ".join(lost)}' if lost else '')
                     + f'; the original is kept as {f.kept_as}')
    if r.metadata is not None:
        lines.append(f'reindex: wrote {r.metadata} ({r.messages} messages in '
                     f'{len(r.files)} file(s))')
    return lines


def run(args) -> int:
    from multicam_ego_motion import interrupt
    interrupt.note(kept=f'{args.bag}: the file being rebuilt is left as it was '
                        '(a rebuilt file only replaces it once complete)')
    result = reindex(args.bag)
    for line in describe(result):
        print(line)
    return 0
