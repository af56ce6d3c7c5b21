"""The figures a suite judges a replay by, and the judging: against limits and a baseline.

Figures are the evaluator's (multicam_ego_motion/evaluation/metrics.py defines them), plus
`abs_scale_error_pct` = |scale_error_pct| and `odometry_share`, the share of played frames
whose stamp has an /odom message. A limit is an upper bound, except for `odometry_share`,
where it is the lowest share allowed.

Against a baseline (the figures of an earlier run), a figure may be worse by
`baseline_tolerance_pct` percent of the baseline's value, and at least by one unit of its
last printed digit (0.001 % for the percentages): a change too small to show is never a
regression. Compared there: the five figures of BASELINE_FIGURES and any other with a limit.
"""
import math
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional


@dataclass(frozen=True)
class Figure:
    label: str
    fmt: str
    higher_is_better: bool = False
    maximum: Optional[float] = None       # largest meaningful limit

    @property
    def resolution(self) -> float:
        """One unit of the last printed digit."""
        decimals = int(self.fmt.split('.')[1].rstrip('f}'))
        return 10.0 ** -decimals

    def format(self, value) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return 'n/a'
        return self.fmt.format(value)


FIGURES = {
    'ate_pct': Figure('ATE RMSE [% of path]', '{:.3f}'),
    'final_drift_pct': Figure('final drift [% of path]', '{:.3f}'),
    'rotation_drift_deg_per_m': Figure('rotation drift [deg/m]', '{:.4f}'),
    'abs_scale_error_pct': Figure('|scale error| [%]', '{:.3f}'),
    'odometry_share': Figure('frames with /odom [share]', '{:.3f}', higher_is_better=True, maximum=1.0),
    'ate_rmse_m': Figure('ATE RMSE [m]', '{:.4f}'),
    'ate_se3_rmse_m': Figure('ATE RMSE after SE(3) fit [m]', '{:.4f}'),
    'ate_sim3_rmse_m': Figure('ATE RMSE after Sim(3) fit [m]', '{:.4f}'),
    'ate_sim3_pct': Figure('ATE RMSE after Sim(3) fit [% of path]', '{:.3f}'),
    'first_odometry_s': Figure('first moving /odom after [s]', '{:.3f}'),
    'final_drift_m': Figure('final drift [m]', '{:.4f}'),
    'rpe_trans_pct': Figure('RPE translation [%]', '{:.3f}'),
    'rpe_rot_deg_per_m': Figure('RPE rotation [deg/m]', '{:.4f}'),
}
BASELINE_FIGURES = ('ate_pct', 'final_drift_pct', 'rotation_drift_deg_per_m',
                    'abs_scale_error_pct', 'odometry_share')


def _clean(value):
    return None if isinstance(value, float) and not math.isfinite(value) else value


def figures_from(metrics: dict, frame_stamps_ns, odom_stamps_s) -> dict:
    """Every figure of FIGURES (None where it could not be computed, e.g. an RPE over a path
    shorter than its shortest segment), plus the counts behind odometry_share."""
    out = {k: _clean(float(metrics[k])) for k in FIGURES if k in metrics}
    out['abs_scale_error_pct'] = _clean(abs(float(metrics['scale_error_pct'])))
    odom_us = {round(s * 1e6) for s in odom_stamps_s}
    frames = sorted(set(frame_stamps_ns))
    # within a microsecond: a stamp in float seconds near 1.7e9 keeps ~0.2 us, so a frame at
    # x.5 us (KITTI's times.txt has 0.1 us) can round to either neighbour
    with_odom = sum(1 for ns in frames if any(round(ns / 1e3) + d in odom_us for d in (-1, 0, 1)))
    out['odometry_share'] = with_odom / len(frames) if frames else 0.0
    out['frames'] = len(frames)
    out['frames_with_odometry'] = with_odom
    out['odometry_poses'] = len(odom_us)
    out['scale_error_pct'] = _clean(float(metrics['scale_error_pct']))
    out['path_length_m'] = float(metrics['path_length_m'])
    return out


COUNTS = ('frames', 'frames_with_odometry', 'odometry_poses')


def mean_of_replays(replays: List[dict]) -> dict:
    """A bag's figures from several replays of it (a suite's `repeat`): each figure the mean
    (None if any replay has none), except those where higher is better (odometry_share) and
    the frame counts, which are the worst replay's: every replay must give every frame its
    /odom. The replays' own figures stay under `replays`."""
    worst = min(replays, key=lambda f: f['odometry_share'])
    out = {}
    for key in replays[0]:
        if key in COUNTS or (key in FIGURES and FIGURES[key].higher_is_better):
            out[key] = worst[key]
            continue
        values = [f.get(key) for f in replays]
        out[key] = None if any(v is None for v in values) else sum(values) / len(values)
    out['replays'] = [dict(f) for f in replays]
    return out


@dataclass
class Check:
    bag: str
    figure: str
    kind: str                       # 'limit' | 'baseline'
    value: Optional[float]
    bound: Optional[float]          # the value allowed at worst; None: nothing to compare with
    passed: bool
    reference: Optional[float] = None     # baseline: the baseline's value
    tolerance_pct: Optional[float] = None
    skipped: bool = False           # baseline: the baseline has no figure for this bag

    @property
    def name(self) -> str:
        """The test case's name: the figure, marked when it is the baseline comparison."""
        return self.figure if self.kind == 'limit' else f'{self.figure} vs baseline'

    @property
    def spec(self) -> Figure:
        return FIGURES.get(self.figure, Figure(self.figure, '{:.3f}'))

    def condition(self) -> str:
        """'<= 0.6', '>= 1.000', '<= 0.331 (baseline 0.301 + 10 %)'."""
        if self.bound is None:
            return 'no baseline for this bag' if self.figure == 'figures' else 'not in the baseline'
        op = '>=' if self.spec.higher_is_better else '<='
        fmt = self.spec.format
        if self.kind == 'limit':
            return f'{op} {self.bound:g}'
        sign = '-' if self.spec.higher_is_better else '+'
        return f'{op} {fmt(self.bound)} (baseline {fmt(self.reference)} {sign} {self.tolerance_pct:g} %)'

    def message(self) -> str:
        """One line naming the bag and the figure: 'loop: ate_pct 0.712, limit <= 0.6: FAIL'."""
        if self.skipped:
            return f'{self.bag}: {self.name}: {self.condition()}: skipped'
        what = 'limit' if self.kind == 'limit' else 'baseline'
        verdict = 'pass' if self.passed else ('skipped' if self.skipped else 'FAIL')
        return (f'{self.bag}: {self.figure} {self.spec.format(self.value)}, {what} '
                f'{self.condition()}: {verdict}')

    def to_json(self) -> dict:
        d = asdict(self)
        d['condition'] = self.condition()
        return d


def _meets(value, bound, higher_is_better) -> bool:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return False
    return value >= bound if higher_is_better else value <= bound


def limit_checks(bag: str, figures: dict, limits: Dict[str, float]) -> List[Check]:
    out = []
    for key, bound in limits.items():
        v = figures.get(key)
        out.append(Check(bag, key, 'limit', v, bound, _meets(v, bound, FIGURES[key].higher_is_better)))
    return out


def baseline_bound(figure: str, reference: float, tolerance_pct: float) -> float:
    spec = FIGURES[figure]
    slack = max(abs(reference) * tolerance_pct / 100.0, spec.resolution)
    return reference - slack if spec.higher_is_better else reference + slack


def baseline_checks(bag: str, figures: dict, baseline: Optional[dict], tolerance_pct: float,
                    limits: Dict[str, float]) -> List[Check]:
    """`baseline`: the baseline's figures of this bag (None: the bag is not in it)."""
    if baseline is None:
        return [Check(bag, 'figures', 'baseline', None, None, True, tolerance_pct=tolerance_pct,
                      skipped=True)]
    keys = list(BASELINE_FIGURES) + [k for k in limits if k not in BASELINE_FIGURES]
    out = []
    for key in keys:
        v = figures.get(key)
        ref = baseline.get(key)
        if ref is None:         # not measured then (or an older baseline): nothing to compare
            out.append(Check(bag, key, 'baseline', v, None, True, tolerance_pct=tolerance_pct,
                             skipped=True))
            continue
        bound = baseline_bound(key, ref, tolerance_pct)
        out.append(Check(bag, key, 'baseline', v, bound,
                         _meets(v, bound, FIGURES[key].higher_is_better), ref, tolerance_pct))
    return out
