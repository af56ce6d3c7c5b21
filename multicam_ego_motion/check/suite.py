"""A regression suite file: which bags to replay, how, and what their figures must meet.

    # my_suite.yaml (paths are relative to this file)
    baseline: my_suite.baseline.json     # optional: figures of an earlier run
    defaults:                            # optional: for every bag (a bag's own keys win;
      workers: 2                         #   limits merge figure by figure)
      limits: {odometry_share: 1.0}
    bags:
      - name: loop                       # optional: the bag folder's or scenario's name
        generate: {scenario: loop, seed: 7, duration: 20, rate: 8, width: 320, height: 240, fx: 200}
        limits: {ate_pct: 0.6, final_drift_pct: 0.7}
      - bag: ../bags/yard                # a recorded bag
        rig: ../config/yard_rig.yaml     # optional (default: BAG/rig.yaml, else /tf_static)
        params: yard_params.yaml         # optional (default: the package's config/params.yaml)
        no_wheel: true                   # optional: do not fuse /wheel/odom
        duration: 60                     # optional: replay only the first 60 s
        baseline_tolerance_pct: 10       # compare with the baseline, 10 % worse allowed
      - name: drive                      # a drive whose figures move by 2x with the last bit
        bag: ../bags/drive               #   of any number (a chaotic case):
        repeat: {quality_level: [0.009, 0.01, 0.011]}   # judge the mean of three replays,
        limits: {ate_pct: 1.8}           #   one per value of this quarter parameter

`repeat`: one parameter of the quarter nodes and 2 to 9 values of it (within its declared
range). The bag is replayed once per value; its figures are the mean over the replays, except
odometry_share and the frame counts, which are the worst replay's (every replay must give
every frame its /odom). Why: on a real drive a monocular map's scale is chaotic, a change in
the last bit anywhere (another CPU's vector unit, a 10 % different feature threshold) moves
one replay's ATE by up to 2x, so one replay cannot tell a regression from that; a mean over
nearby settings can.

Every error names the file, the bag entry and the key.
"""
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

from multicam_ego_motion.check.bags import GenerateSpec, KittiSpec
from multicam_ego_motion.check.figures import FIGURES
from multicam_ego_motion.errors import UserError

DEFAULT_WORKERS = 2
DEFAULT_GROUND_TRUTH_TOPIC = '/ground_truth/odom'
SUITE_KEYS = ('bags', 'defaults', 'baseline')
# keys `defaults:` may give every bag
SHARED_KEYS = ('rig', 'params', 'workers', 'no_wheel', 'duration', 'limits',
               'baseline_tolerance_pct', 'ground_truth_topic', 'repeat')
REPEAT_VALUES = (2, 9)       # how many values a `repeat` may give
BAG_KEYS = ('name', 'bag', 'generate', 'import_kitti') + SHARED_KEYS
SOURCES = ('bag', 'generate', 'import_kitti')     # exactly one per entry
IMPORT_KITTI_KEYS = {'folder': str, 'every': int, 'no_stereo': bool, 'halves': bool}
GENERATE_KEYS = {'scenario': str, 'seed': int, 'duration': float, 'rate': float, 'width': int,
                 'height': int, 'fx': float, 'k1': float, 'cameras': int}
NAME_PATTERN = re.compile(r'^[A-Za-z0-9][A-Za-z0-9_.-]*$')


@dataclass(frozen=True)
class Repeat:
    """Replay once per value of one quarter-node parameter, judge the mean."""
    parameter: str
    values: tuple

    def labels(self) -> List[str]:
        """One folder name per replay: 'quality_level=0.009'."""
        return [f'{self.parameter}={v:g}' for v in self.values]


@dataclass
class BagEntry:
    name: str
    bag: Optional[Path]                    # None: generated (see `generate`) or imported
    generate: Optional[GenerateSpec]
    import_kitti: Optional[KittiSpec] = None
    rig: Optional[Path] = None
    params: Optional[Path] = None
    workers: int = DEFAULT_WORKERS
    no_wheel: bool = False
    duration: Optional[float] = None
    limits: Dict[str, float] = field(default_factory=dict)
    baseline_tolerance_pct: Optional[float] = None
    ground_truth_topic: str = DEFAULT_GROUND_TRUTH_TOPIC
    repeat: Optional[Repeat] = None

    @property
    def uses_baseline(self) -> bool:
        return self.baseline_tolerance_pct is not None


@dataclass
class Suite:
    path: Path
    bags: List[BagEntry]
    baseline: Optional[Path] = None

    @property
    def name(self) -> str:
        return self.path.stem


class _Where:
    """Names the place of an error: 'suite.yaml: bags[2] (corridor): limits.ate_pct'."""

    def __init__(self, path: Path, entry: Optional[str] = None):
        self.path, self.entry = path, entry

    def error(self, key: Optional[str], text: str) -> UserError:
        where = str(self.path) + (f': {self.entry}' if self.entry else '')
        return UserError(f'{where}: {key + ": " if key else ""}{text}')


def _number(where, key, value, minimum=None, maximum=None, integer=False):
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok or (not integer and not math.isfinite(value)):
        raise where.error(key, f'expected {"an integer" if integer else "a number"}, got {value!r}')
    if minimum is not None and value < minimum or maximum is not None and value > maximum:
        span = (f'between {minimum:g} and {maximum:g}' if maximum is not None
                else f'at least {minimum:g}')
        raise where.error(key, f'must be {span}, got {value!r}')
    return value


def _mapping(where, key, value) -> dict:
    if not isinstance(value, dict):
        raise where.error(key, f'expected a mapping (key: value), got {type(value).__name__} {value!r}')
    return value


def _unknown_keys(where, prefix, given, allowed):
    for k in given:
        if k not in allowed:
            raise where.error(f'{prefix}{k}', f'unknown key (expected one of: {", ".join(allowed)})')


def _file(where, key, value, base: Path) -> Path:
    if not isinstance(value, str) or not value:
        raise where.error(key, f'expected a path, got {value!r}')
    path = (base / value).resolve()
    if not path.exists():
        raise where.error(key, f'{path} not found')
    return path


def _limits(where, value) -> Dict[str, float]:
    limits = _mapping(where, 'limits', value)
    _unknown_keys(where, 'limits.', limits, tuple(FIGURES))
    out = {}
    for k, v in limits.items():
        out[k] = float(_number(where, f'limits.{k}', v, 0.0, FIGURES[k].maximum))
    return out


def _repeat(where, value) -> Repeat:
    from camera_pose_nodes.quarter_estimator import PARAMETERS
    spec = _mapping(where, 'repeat', value)
    if len(spec) != 1:
        raise where.error('repeat', f'expected one quarter parameter and its values, got {len(spec)} keys')
    (name, values), = spec.items()
    if name not in PARAMETERS:
        raise where.error('repeat', f'{name!r} is not a parameter of the quarter nodes')
    default, _, low, high = PARAMETERS[name]
    if isinstance(default, (bool, str)):
        raise where.error('repeat', f'{name!r} is not a number (repeat varies a numeric parameter)')
    lo, hi = REPEAT_VALUES
    if not isinstance(values, list) or not lo <= len(values) <= hi:
        raise where.error(f'repeat.{name}', f'expected a list of {lo} to {hi} values, got {values!r}')
    integer = isinstance(default, int)         # (bool and str refused above)
    out = tuple(_number(where, f'repeat.{name}', v, low, high, integer=integer) for v in values)
    if len(set(out)) != len(out):
        raise where.error(f'repeat.{name}', f'the same value twice in {values!r}')
    return Repeat(name, out)


def _generate(where, value) -> GenerateSpec:
    from types import SimpleNamespace

    from multicam_ego_motion.scenarios.generator import validate
    gen = _mapping(where, 'generate', value)
    _unknown_keys(where, 'generate.', gen, tuple(GENERATE_KEYS))
    if 'scenario' not in gen:
        raise where.error('generate', 'needs a scenario')
    kw = {}
    for k, v in gen.items():
        kind = GENERATE_KEYS[k]
        if kind is str:
            if not isinstance(v, str):
                raise where.error(f'generate.{k}', f'expected a name, got {v!r}')
            kw[k] = v
        else:
            kw[k] = kind(_number(where, f'generate.{k}', v, integer=kind is int))
    spec = GenerateSpec(**kw)
    try:
        validate(SimpleNamespace(**spec.__dict__))
    except UserError as e:       # the generator's words name its command-line options
        raise where.error('generate', str(e).replace('--', '')) from None
    if not 1 <= spec.cameras <= 8:
        raise where.error('generate.cameras', f'must be between 1 and 8, got {spec.cameras}')
    return spec


def _import_kitti(where, value, base: Path) -> KittiSpec:
    spec = _mapping(where, 'import_kitti', value)
    _unknown_keys(where, 'import_kitti.', spec, tuple(IMPORT_KITTI_KEYS))
    if 'folder' not in spec:
        raise where.error('import_kitti', 'needs a folder (a KITTI sequence)')
    folder = _file(where, 'import_kitti.folder', spec['folder'], base)
    for k in ('no_stereo', 'halves'):
        if not isinstance(spec.get(k, False), bool):
            raise where.error(f'import_kitti.{k}', f'expected true or false, got {spec[k]!r}')
    every = _number(where, 'import_kitti.every', spec.get('every', 1), 1, 100, integer=True)
    return KittiSpec(folder, every, spec.get('no_stereo', False), spec.get('halves', False))


def _shared(where, raw: dict, base: Path) -> dict:
    """The SHARED_KEYS of a bag entry or of `defaults:`, checked and converted."""
    out = {}
    for key in SHARED_KEYS:
        if key not in raw:
            continue
        v = raw[key]
        if key in ('rig', 'params'):
            out[key] = _file(where, key, v, base)
        elif key == 'workers':
            out[key] = _number(where, key, v, 1, 64, integer=True)
        elif key == 'no_wheel':
            if not isinstance(v, bool):
                raise where.error(key, f'expected true or false, got {v!r}')
            out[key] = v
        elif key == 'duration':
            out[key] = float(_number(where, key, v, 0.1))
        elif key == 'limits':
            out[key] = _limits(where, v)
        elif key == 'baseline_tolerance_pct':
            out[key] = float(_number(where, key, v, 0.0))
        elif key == 'repeat':
            out[key] = _repeat(where, v)
        elif key == 'ground_truth_topic':
            if not isinstance(v, str) or not v.startswith('/'):
                raise where.error(key, f'expected a topic name (/...), got {v!r}')
            out[key] = v
    return out


def _entry(path: Path, index: int, raw, defaults: dict) -> BagEntry:
    base = path.parent
    label = f'bags[{index}]'
    if isinstance(raw, dict) and isinstance(raw.get('name'), str):
        label += f' ({raw["name"]})'
    elif isinstance(raw, dict) and isinstance(raw.get('bag'), str):
        label += f' ({raw["bag"]})'
    where = _Where(path, label)
    raw = _mapping(where, None, raw)
    _unknown_keys(where, '', raw, BAG_KEYS)
    given = [k for k in SOURCES if k in raw]
    if len(given) != 1:
        raise where.error(None, 'give one of bag (a bag folder), generate (a scenario) or '
                                'import_kitti (a KITTI sequence), not '
                                + (' and '.join(given) if given else 'none'))
    bag = _file(where, 'bag', raw['bag'], base) if 'bag' in raw else None
    if bag is not None and not bag.is_dir():
        raise where.error('bag', f'{bag} is not a bag folder')
    spec = _generate(where, raw['generate']) if 'generate' in raw else None
    kitti = _import_kitti(where, raw['import_kitti'], base) if 'import_kitti' in raw else None
    own = _shared(where, raw, base)
    values = {**defaults, **own}
    own_limits = own.get('limits', {})
    values['limits'] = {**own_limits, **{k: v for k, v in defaults.get('limits', {}).items()
                                         if k not in own_limits}}
    name = raw.get('name')
    if name is None:
        name = bag.name if bag is not None else spec.scenario if spec is not None else kitti.folder.name
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        raise where.error('name', f'{name!r}: use letters, digits, ".", "_" and "-" '
                                  '(it names the output folder and the test cases)')
    entry = BagEntry(name=name, bag=bag, generate=spec, import_kitti=kitti, **values)
    if not entry.limits and not entry.uses_baseline:
        raise where.error(None, 'nothing to check: give limits or baseline_tolerance_pct')
    return entry


def parse_suite(path: Path, doc) -> Suite:
    where = _Where(path)
    if not isinstance(doc, dict):
        raise where.error(None, 'expected a mapping with a list of bags under "bags"')
    _unknown_keys(where, '', doc, SUITE_KEYS)
    defaults_raw = _mapping(where, 'defaults', doc.get('defaults') or {})
    _unknown_keys(_Where(path, 'defaults'), '', defaults_raw, SHARED_KEYS)
    defaults = _shared(_Where(path, 'defaults'), defaults_raw, path.parent)
    bags_raw = doc.get('bags')
    if not isinstance(bags_raw, list) or not bags_raw:
        raise where.error('bags', 'expected a non-empty list of bag entries')
    bags = [_entry(path, i, raw, defaults) for i, raw in enumerate(bags_raw)]
    seen = {}
    for i, e in enumerate(bags):
        if e.name in seen:
            raise _Where(path, f'bags[{i}] ({e.name})').error(
                'name', f'same name as bags[{seen[e.name]}]: give each entry its own name')
        seen[e.name] = i
    baseline = None
    if doc.get('baseline') is not None:
        value = doc['baseline']
        if not isinstance(value, str) or not value:
            raise where.error('baseline', f'expected a path, got {value!r}')
        baseline = (path.parent / value).resolve()   # may not exist yet (--update-baseline)
    return Suite(path, bags, baseline)


def load_suite(path) -> Suite:
    import yaml
    path = Path(path)
    if not path.is_file():
        raise UserError(f'suite file not found: {path}')
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, 'problem_mark', None)
        at = f' at line {mark.line + 1}, column {mark.column + 1}' if mark else ''
        raise UserError(f'{path}: not valid YAML{at} ({getattr(e, "problem", None) or e})') from None
    return parse_suite(path, doc)
