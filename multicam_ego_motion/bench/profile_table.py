"""`ego-motion profile BAG --out DIR`: where the sequential pipeline's CPU goes, as one table of
stage x kind of work (OpenCV, library math, Python bookkeeping, message conversion), in ms per
frame, and the top functions by own time. Writes DIR/profile.md and the raw cProfile dump
DIR/sequential.prof (read it with `pstats`). With --graph, one short lockstep run of the
graph at M = 2 adds the row the one-process profile cannot see: ROS transport.

How a function's own time (cProfile's tottime) is attributed:

- Stage: up the call graph to the nearest stage root (STAGE_ROOTS, matched by file name and
  function name, so that functions added or renamed below a root change nothing). A function
  called from several places is split among its callers in proportion to the time it spent
  under each (the per-caller own time cProfile records for the first step up, the per-caller
  cumulative time above); recursion is cut where a caller is already on the path. Functions
  defined inside a root (closures) belong to it. Time that reaches no root (set-up, the
  pipeline's own loop) is "other". Each function's time is CPU time of the (single) thread.
- Kind: where the function lives (KIND_BY_PATH, builtins by name). Project code is Python
  bookkeeping. Code that belongs to nobody in particular (Python builtins such as len or
  list.append, the standard library, other libraries such as yaml) is counted as the kind of
  whoever called it: list.append inside mcap is bag reading, inside the quarter estimator it
  is bookkeeping.
"""
import ast
import functools
import os
import re
import sys
import sysconfig
import time
from collections import defaultdict
from pathlib import Path

from multicam_ego_motion.errors import UserError

# ---- what the table is made of ---------------------------------------------------------------

BAG = 'bag reading and image decoding'
MSG = 'message conversion'
OTHER = 'other'
# The single source of truth for stages: (file name, function name) -> stage. The nearest root
# on a call path wins (flow/track/extract under process_image count as track/extract).
STAGE_ROOTS = {
    ('rosbag2_reader.py', '__init__'): BAG,           # opening the bag (metadata)
    ('rosbag2_reader.py', 'decoded'): BAG,
    ('image_conversion.py', 'image_msg_to_gray'): BAG,
    ('image_conversion.py', 'to_gray'): BAG,
    ('klt_tracker.py', 'flow'): 'track',
    ('klt_tracker.py', 'track'): 'track',
    ('klt_tracker.py', 'extract'): 'extract',
    ('quarter_estimator.py', 'process_image'): 'pose',
    ('quarter_estimator.py', 'apply_fused_pose'): 'structure',
    ('quarter_fusion.py', 'fuse_quarters'): 'camera arbiter',
    ('general_fusion.py', 'process'): 'general arbiter',
    ('sequential_pipeline.py', 'as_received'): MSG,   # estimate -> ROS message -> estimate
    ('pose_messages.py', 'estimate_to_msg'): MSG,
    ('pose_messages.py', 'msg_to_estimate'): MSG,
}
STAGES = (BAG, 'track', 'extract', 'pose', 'structure', 'camera arbiter', 'general arbiter', MSG, OTHER)

OPENCV, MATH, PYTHON, ROSMSG = 'OpenCV', 'library math', 'Python bookkeeping', 'message conversion'
KINDS = (OPENCV, MATH, PYTHON, ROSMSG)
KIND_TITLES = {OPENCV: 'OpenCV', MATH: 'library math (numpy, scipy, filterpy)',
               PYTHON: 'Python bookkeeping', ROSMSG: 'message conversion (rclpy, messages, bag)'}
# Python code by where it lives (regex on the path, first match wins).
KIND_BY_PATH = (
    (re.compile(r'[\\/]cv2[\\/]'), OPENCV),
    (re.compile(r'[\\/](numpy|scipy|filterpy)[\\/]'), MATH),
    (re.compile(r'[\\/](rclpy|rosidl\w*|rpyutils|mcap\w*|rosbags|zstandard|lz4)[\\/]'), ROSMSG),
    (re.compile(r'[\\/]\w+[\\/]msg[\\/]_\w+\.py$'), ROSMSG),           # generated message classes
    (re.compile(r'[\\/]multicam_ego_motion[\\/](bag[\\/]rosbag2_reader|ros_plumbing[\\/]pose_messages)\.py$'), ROSMSG),
    (re.compile(r'[\\/](camera_pose_nodes|arbiter_node|multicam_ego_motion)[\\/]'), PYTHON),
)
# Builtins (C functions) by their label.
KIND_BY_BUILTIN = (
    (re.compile(r'\bcv2\.'), OPENCV),
    (re.compile(r'\b(numpy|scipy)\.'), MATH),
    (re.compile(r'\b(_?rclpy|rosidl\w*|zstandard|zstd|lz4|mcap)\b'), ROSMSG),
)
MAX_DEPTH = 100     # hops up the call graph before giving up ("other")


def _cv2_names():
    try:
        import cv2
    except ImportError:
        return frozenset()
    return frozenset(n for n in dir(cv2) if not n.startswith('_'))


_CV2 = None


def _stdlib_prefixes():
    paths = {sysconfig.get_paths()[k] for k in ('stdlib', 'platstdlib')}
    return tuple(str(Path(p)) + os.sep for p in paths if p)


_STDLIB = _stdlib_prefixes()


def kind_of(func):
    """The kind of a pstats function key (file, line, name), or None: counted as its callers'."""
    global _CV2
    path, _, name = func
    if path == '~':
        for pattern, kind in KIND_BY_BUILTIN:
            if pattern.search(name):
                return kind
        # cv2's functions have bare labels: <calcOpticalFlowPyrLK>
        m = re.fullmatch(r'<(\w+)>', name)
        if m:
            if _CV2 is None:
                _CV2 = _cv2_names()
            if m.group(1) in _CV2:
                return OPENCV
        return None
    for pattern, kind in KIND_BY_PATH:
        if pattern.search(path):
            return kind
    return None      # the standard library, other libraries (yaml, tqdm, ...): on behalf of the caller


def root_of(func, roots=None):
    """The stage of a root, else None. Functions defined inside a root (closures such as the
    tracker's per-chunk LK call and per-cell corner search) are roots of its stage too: they
    run on its behalf, and a helper shared by two roots that calls them (the tracker's _map)
    would otherwise split them by the helper's time under either root (cProfile keeps one
    level of callers)."""
    roots = STAGE_ROOTS if roots is None else roots
    path, line, name = func
    base = os.path.basename(path)
    stage = roots.get((base, name))
    if stage is not None or path == '~':
        return stage
    names = tuple(sorted(n for b, n in roots if b == base))
    if not names:
        return None
    inside = [(start, roots[(base, n)]) for start, end, n in _definitions(path, names)
              if start < line <= end]
    return max(inside)[1] if inside else None        # the innermost


@functools.lru_cache(maxsize=None)
def _definitions(path, names):
    """(first line, last line, name) of the functions called `names` in a source file."""
    try:
        tree = ast.parse(Path(path).read_text())
    except (OSError, SyntaxError, ValueError):
        return ()
    return tuple((min([n.lineno] + [d.lineno for d in n.decorator_list]), n.end_lineno, n.name)
                 for n in ast.walk(tree)
                 if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name in names)


# ---- attribution ---------------------------------------------------------------------------------

class _Graph:
    """Distributions over stages and kinds up the caller graph of pstats-like stats:
    {func: (cc, nc, tt, ct, {caller: (nc, cc, tt, ct)})}."""

    def __init__(self, stats, roots=None, kinds=None):
        self.stats = stats
        self.root = (lambda f: root_of(f, roots))
        self.kind = kinds or kind_of
        self._stage_memo, self._kind_memo = {}, {}

    def callers(self, f, col):
        """{caller: weight} by the per-caller column `col` (2 own time, 3 cumulative), falling
        back to the cumulative time and then to call counts when the times are all zero."""
        callers = {c: v for c, v in (self.stats[f][4] if f in self.stats else {}).items() if c != f}
        for k in (col, 3, 0):
            w = {c: float(v[k]) for c, v in callers.items() if v[k] > 0}
            if w:
                return w
        return {}

    def _up(self, f, own, memo, path, depth, default):
        """(distribution of f's share over labels, cut): its own label when `own(f)` has one,
        else its callers', weighted by their cumulative times. A caller already on the path
        (recursion) is left out; None when every caller is: the path only cycles back, and
        the step that came here is left out in turn."""
        label = own(f)
        if label is not None:
            return {label: 1.0}, False
        if f in memo:
            return memo[f], False
        if depth >= MAX_DEPTH:
            return {default: 1.0}, True
        weights = self.callers(f, 3)
        if not weights:
            return {default: 1.0}, False          # the top of the profile
        path.add(f)
        cut = False
        dist, total = defaultdict(float), 0.0
        for c, w in weights.items():
            if c in path:
                cut = True
                continue
            d, c_cut = self._up(c, own, memo, path, depth + 1, default)
            cut |= c_cut
            if d is None:
                continue
            total += w
            for k, v in d.items():
                dist[k] += v * w
        path.discard(f)
        result = {k: v / total for k, v in dist.items()} if total > 0 else None
        if not cut:          # a result computed with part of the graph cut is path dependent
            memo[f] = result
        return result, cut

    def _dist(self, f, own, memo, default):
        d = self._up(f, own, memo, set(), 0, default)[0]
        return d if d is not None else {default: 1.0}

    def stage_dist(self, f):
        return self._dist(f, self.root, self._stage_memo, OTHER)

    def kind_dist(self, f):
        return self._dist(f, self.kind, self._kind_memo, PYTHON)


def attribute(stats, roots=None, kinds=None):
    """{(stage, kind): seconds} of every function's own time (tottime) in pstats-like `stats`.
    The cells add up to the total own time."""
    g = _Graph(stats, roots, kinds)
    cells = defaultdict(float)
    for f, (_, _, tt, _, _) in stats.items():
        if tt <= 0:
            continue
        own_stage, own_kind = g.root(f), g.kind(f)
        if own_stage is not None and own_kind is not None:
            cells[(own_stage, own_kind)] += tt
            continue
        # The first step up splits the function's own time by what it spent under each caller.
        weights = g.callers(f, 2)
        total = sum(weights.values())
        if total <= 0:
            cells[(own_stage or OTHER, own_kind or PYTHON)] += tt
            continue
        for c, w in weights.items():
            stages = {own_stage: 1.0} if own_stage is not None else g.stage_dist(c)
            kinds = {own_kind: 1.0} if own_kind is not None else g.kind_dist(c)
            for s, ps in stages.items():
                for k, pk in kinds.items():
                    cells[(s, k)] += tt * w / total * ps * pk
    return dict(cells)


def _main_stage(g, f):
    """The stage that gets most of f's own time (for the top-functions listing)."""
    if g.root(f) is not None:
        return g.root(f)
    weights = g.callers(f, 2)
    total = sum(weights.values())
    dist = defaultdict(float)
    for c, w in weights.items():
        for s, p in g.stage_dist(c).items():
            dist[s] += p * w / total
    return max(dist, key=dist.get) if dist else OTHER


# ---- tables ----------------------------------------------------------------------------------------

def func_label(func):
    path, line, name = func
    if path == '~':
        return '{' + name.strip('<>') + '}' if name.startswith('<') else name
    p = Path(path)
    parts = p.parts
    for anchor in ('site-packages', 'camera_pose_nodes', 'arbiter_node', 'multicam_ego_motion'):
        if anchor in parts:
            i = len(parts) - 1 - parts[::-1].index(anchor)
            rel = '/'.join(parts[i + 1:] if anchor == 'site-packages' else parts[i:])
            return f'{rel}:{line}({name})'
    return f'{p.name}:{line}({name})'


def stage_table(cells, frames):
    per = {k: v / frames * 1e3 for k, v in cells.items()}
    grand = sum(per.values())
    head = ['| stage [ms per frame] | ' + ' | '.join(KIND_TITLES[k] for k in KINDS) + ' | total | share |',
            '|---|' + '---:|' * (len(KINDS) + 2)]
    rows = []
    for s in STAGES:
        vals = [per.get((s, k), 0.0) for k in KINDS]
        rows.append(f'| {s} | ' + ' | '.join(f'{v:.2f}' for v in vals)
                    + f' | {sum(vals):.2f} | {100 * sum(vals) / grand if grand else 0:.1f} % |')
    tot = [sum(per.get((s, k), 0.0) for s in STAGES) for k in KINDS]
    rows.append('| **total** | ' + ' | '.join(f'{v:.2f}' for v in tot) + f' | {grand:.2f} | 100 % |')
    return head + rows


def top_functions(stats, frames, n=15):
    total = sum(v[2] for v in stats.values()) or 1.0
    top = sorted(stats.items(), key=lambda kv: -kv[1][2])[:n]
    lines = ['| own time [ms per frame] | share | calls per frame | cumulative [ms per frame] '
             '| kind | stage (most of it) | function |', '|---:|---:|---:|---:|---|---|---|']
    g = _Graph(stats)
    for f, (cc, nc, tt, ct, _) in top:
        kind = g.kind(f)
        if kind is None:
            d = defaultdict(float)
            weights = g.callers(f, 2)
            tw = sum(weights.values()) or 1.0
            for c, w in weights.items():
                for k, p in g.kind_dist(c).items():
                    d[k] += p * w / tw
            kind = max(d, key=d.get) if d else PYTHON
        lines.append(f'| {tt / frames * 1e3:.2f} | {100 * tt / total:.1f} % | {nc / frames:.1f} '
                     f'| {ct / frames * 1e3:.2f} | {kind} | {_main_stage(g, f)} | `{func_label(f)}` |')
    return lines


# ---- the command -----------------------------------------------------------------------------------

def configure_parser(p):
    p.add_argument('bag', help='rosbag2 MCAP bag (folder)')
    p.add_argument('--out', required=True, help='output folder (profile.md, sequential.prof)')
    p.add_argument('--frames', type=int, metavar='N', help='profile only the first N frames')
    p.add_argument('--rig', help='rig YAML (default: from the bag\'s rig.yaml or /tf_static)')
    p.add_argument('--params', help='ROS params file (default: the package\'s config/params.yaml)')
    p.add_argument('--graph', action='store_true',
                   help='also run the graph in lockstep at M = 2 over the same frames for the ROS '
                        'transport row (about a minute on the default bag)')


def _sequential(bag, rig, qp, fp, frames, label, profiler=None):
    """One run of the sequential pipeline (OpenCV on one thread); (result, CPU s, wall s)."""
    import cv2
    from tqdm import tqdm

    from multicam_ego_motion.sequential_pipeline import run_sequential
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)               # one processor, as the bench's baseline and each worker
    try:
        with tqdm(total=frames, desc=label, unit='frame', file=sys.stderr, mininterval=1.0) as bar:
            t0, c0 = time.perf_counter(), time.process_time()
            if profiler is not None:
                profiler.enable()
            try:
                res = run_sequential(bag, rig, qp, fp, max_frames=frames, progress=bar)
            finally:
                if profiler is not None:
                    profiler.disable()
            return res, time.process_time() - c0, time.perf_counter() - t0
    finally:
        cv2.setNumThreads(threads)


def _trigger_frames(bag):
    from multicam_ego_motion.bag.player import BagPlayer, PlayOptions
    player = BagPlayer(bag, PlayOptions(lockstep=True))
    return player, [f for f in player.frames() if f.is_trigger]


def run(args) -> int:
    import cProfile
    import pstats

    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import fusion_params_from, quarter_params_from
    from multicam_ego_motion.ros_plumbing.package_share import default_params
    from multicam_ego_motion.replay import resolve_rig

    if args.frames is not None and args.frames < 1:
        raise UserError('--frames must be at least 1')
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise UserError(f'output folder {out} is not empty')
    params = Path(args.params) if args.params else default_params()
    if not params.exists():
        raise UserError(f'params file not found: {params}')
    reader = Rosbag2Reader(args.bag)
    rig, rig_file = resolve_rig(reader, args.rig)
    qp, fp = quarter_params_from(params), fusion_params_from(params)
    player, window = _trigger_frames(args.bag)
    n_frames = min(args.frames, len(window)) if args.frames else len(window)
    if not n_frames:
        raise UserError(f'bag {args.bag} has no image frames')
    out.mkdir(parents=True, exist_ok=True)

    # 1. un-profiled: the CPU per frame the profile inflates. A first frame before it takes the
    # one-time imports and initialisations out of both runs.
    print(f'profile: sequential pipeline, {n_frames} frames, without the profiler ...', flush=True)
    _sequential(args.bag, rig, qp, fp, 1, 'warm-up')
    res, cpu_s, wall_s = _sequential(args.bag, rig, qp, fp, n_frames, 'un-profiled')
    frames = len(res.fused)
    cpu_ms, wall_ms = cpu_s / frames * 1e3, wall_s / frames * 1e3
    # 2. profiled
    print('profile: sequential pipeline under cProfile ...', flush=True)
    # CPU time of this (the only) thread, as the stage times in /diagnostics: on a shared
    # machine the default wall clock charged other processes' time to whatever ran meanwhile.
    profiler = cProfile.Profile(time.thread_time)
    res_p, pcpu_s, _ = _sequential(args.bag, rig, qp, fp, n_frames, 'profiled', profiler)
    if len(res_p.fused) != frames:
        raise RuntimeError(f'the profiled run processed {len(res_p.fused)} frames, the other {frames}')
    profiler.dump_stats(out / 'sequential.prof')
    stats = pstats.Stats(str(out / 'sequential.prof')).stats
    print('profile: attributing ...', flush=True)
    cells = attribute(stats)
    total_tt = sum(v[2] for v in stats.values())
    # 3. the graph: what transport costs on top
    graph = None
    if args.graph:
        graph = _graph_transport(args, out, rig, rig_file, params, window, n_frames, player)

    lines = [f'# ego-motion profile: {args.bag}, {frames} frames, sequential pipeline '
             '(one process, OpenCV on one thread)', '',
             f'Stage x kind of work: own time (cProfile tottime, CPU time) of every function, in ms per frame. '
             f'Profiled total {total_tt / frames * 1e3:.1f} ms per frame '
             f'(CPU {pcpu_s / frames * 1e3:.1f} ms per frame under the profiler); '
             f'**without the profiler: {cpu_ms:.1f} ms of CPU per frame** ({wall_ms:.1f} ms wall).', '']
    lines += stage_table(cells, frames)
    if graph is not None:
        g_cpu, g_workers, g_replay, g_frames = graph
        lines += [f'| ROS transport (graph at M = 2) | | | | | {g_cpu - cpu_ms:.2f} | '
                  f'{100 * (g_cpu - cpu_ms) / cpu_ms:+.0f} % on the un-profiled CPU |']
    lines += ['', 'Notes:',
              f'- cProfile inflates Python-call-heavy code (each Python call pays the profiler\'s '
              f'hook; one OpenCV call with a long C body hardly does): the run took '
              f'{pcpu_s / frames * 1e3:.1f} ms of CPU per frame profiled against {cpu_ms:.1f} ms '
              f'without ({pcpu_s / cpu_s:.2f} x). The OpenCV column is close to its real cost; '
              'the Python columns are too high by most of that difference.',
              '- numpy arithmetic written as operators (a @ b, a + b, indexing) is not a call '
              'cProfile sees: it counts as the own time of the Python function that does it '
              '(Python bookkeeping); numpy/scipy functions and numpy methods count as library math.',
              '- Stages by the call graph: a function called from several stages is split by the '
              'time it spent under each; "other" is set-up (estimators, filters) and the '
              'pipeline\'s own loop. Bag reading includes decompressing and deserializing the '
              'image messages; "message conversion" is the estimate -> ROS message -> estimate '
              'round trip of every quarter, camera and fused estimate.']
    if graph is not None:
        lines.append(f'- ROS transport (graph at M = 2): lockstep graph over the same {g_frames} '
                     f'frames, CPU per frame of the workers ({g_workers:.1f} ms) + player, '
                     f'recorder and coordinator ({g_replay:.1f} ms) = {g_cpu:.1f} ms, minus the '
                     f'sequential pipeline without the profiler ({cpu_ms:.1f} ms). Not profiled: '
                     'not comparable with the profiled rows above, only with the un-profiled '
                     'CPU per frame.')
    else:
        lines.append('- ROS transport between the graph\'s processes is not in a one-process '
                     'profile: --graph adds it from a lockstep run of the graph at M = 2.')
    lines += ['', f'Top 15 functions by own time (ms per frame; cProfile listing: '
              f'`python -m pstats {out / "sequential.prof"}`):', '']
    lines += top_functions(stats, frames)
    text = '\n'.join(lines) + '\n'
    (out / 'profile.md').write_text(text)
    print(text, end='')
    return 0


def _graph_transport(args, out, rig, rig_file, params, window, n_frames, player):
    """(graph CPU per frame, workers, player+recorder+coordinator, frames) of a lockstep run
    at M = 2 over the profiled frames."""
    from multicam_ego_motion.ros_plumbing import dds_transport, ros_domain
    from multicam_ego_motion.replay import run_graph
    ros_domain.isolate()
    dds_transport.use_graph_profile()
    if rig_file is None:
        rig_file = out / 'rig.yaml'
        rig.save(rig_file)
    # The player's window ends before the first frame left out (its end is exclusive).
    duration = ((window[n_frames].log_time_ns - player.start_ns) / 1e9
                if n_frames < len(window) else None)
    print(f'profile: graph, lockstep, M = 2, {n_frames} frames ...', flush=True)
    g = run_graph(args.bag, out / 'graph_m2', rig, rig_file, params, 2, lockstep=True, rate=1.0,
                  duration=duration, rebalance=False, logger=None, record_topics=['/odom'])
    frames = len(g.playback.published_at) if g.playback else 0
    if not frames:
        raise UserError('the graph run published no frames')
    workers, replay = g.cpu_workers_s / frames * 1e3, g.cpu_replay_s / frames * 1e3
    return workers + replay, workers, replay, frames
