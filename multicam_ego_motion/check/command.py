"""`ego-motion check SUITE.yaml --out DIR`: replay every bag of a regression suite through the
graph (lockstep: deterministic), score it against its ground truth, judge the figures
against the suite's limits and a baseline, and report.

Prints one table (bag, figure, value, limit / baseline, result) and writes into DIR:
results.json (every figure of every bag: a later run's --baseline), summary.md (the table,
links to the plots), junit.xml (one test case per bag x figure, for any CI system) and, per
bag, DIR/<bag>/ with the replay's output bag, odometry.tum, report.md and its plots
(trajectory.png, error_over_distance.png). Exit code 0 when every check passes, 1 on any
regression (the last line names each failing bag and figure), 2 on bad input (the suite,
a bag, a baseline), found before any bag is replayed. `--update-baseline` writes the run's
figures as the new baseline. The suite file's format: multicam_ego_motion/check/suite.py.
"""
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from multicam_ego_motion.check.bags import cached_bag, default_cache, ensure_generated, is_complete
from multicam_ego_motion.check.baseline import load_baseline, write_baseline
from multicam_ego_motion.check.figures import (FIGURES, baseline_checks, figures_from, limit_checks,
                                               mean_of_replays)
from multicam_ego_motion.check.report import (BagResult, markdown_table, table_rows, verdict_line,
                                              write_reports)
from multicam_ego_motion.check.suite import BagEntry, load_suite
from multicam_ego_motion.errors import UserError

MARKER = '.ego-motion-check'     # an output folder a check wrote (and may write again)
REPORT_FILES = ('results.json', 'summary.md', 'junit.xml')


def configure_parser(p):
    p.add_argument('suite', help='suite YAML: bags, how to replay them, the limits their figures must meet')
    p.add_argument('--out', required=True, help='output folder (results.json, summary.md, junit.xml, '
                                                'one folder per bag)')
    p.add_argument('--bags-cache', metavar='DIR',
                   help=f'where bags the suite generates are kept (default {default_cache()})')
    p.add_argument('--baseline', metavar='FILE',
                   help="baseline file: an earlier run's results.json (default: the suite's baseline:)")
    p.add_argument('--update-baseline', action='store_true',
                   help='write this run\'s figures as the baseline (limits are still checked)')
    p.add_argument('--only', nargs='+', metavar='NAME', help='check only these bags of the suite')


@dataclass
class PreparedBag:
    entry: BagEntry
    bag: Path
    rig: object
    rig_file: Path
    params: Path


def check_out(out: Path):
    """An empty (or new) folder, or one an earlier check wrote."""
    if out.exists() and not out.is_dir():
        raise UserError(f'output {out} is a file')
    if out.exists() and any(out.iterdir()) and not (out / MARKER).exists():
        raise UserError(f'output folder {out} is not empty (and not an earlier check\'s)')


def prepare_out(out: Path, names):
    """Empty what an earlier check wrote there: its reports and these bags' folders."""
    import shutil
    check_out(out)
    for f in REPORT_FILES:
        (out / f).unlink(missing_ok=True)
    for name in names:
        if (out / name).exists():
            shutil.rmtree(out / name)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text('written by ego-motion check: it empties this folder\'s bag folders on its next run\n')


def prepare(entry: BagEntry, suite, cache: Path, label: str) -> PreparedBag:
    """Generate the bag when the suite describes it by scenario, and check it can be
    replayed and scored; errors name the suite and the bag entry."""
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay import check_camera_topic_types, resolve_rig
    from multicam_ego_motion.ros_plumbing.package_share import default_params
    try:
        spec = entry.generate or entry.import_kitti
        if spec is not None:
            if not is_complete(cached_bag(cache, spec)):
                print(f'check: {label}: making {spec.describe()} into {cache}', flush=True)
            bag = ensure_generated(cache, spec)
        else:
            bag = entry.bag
        reader = Rosbag2Reader(bag)
        rig, rig_file = resolve_rig(reader, str(entry.rig) if entry.rig else None)
        check_camera_topic_types(reader, rig)
        if not any(c.input_topic in reader.topics for c in rig.cameras):
            raise UserError(f'bag {bag} has none of the rig\'s image topics')
        if entry.ground_truth_topic not in reader.topics:
            raise UserError(f'bag {bag} has no {entry.ground_truth_topic}: nothing to score against')
    except UserError as e:
        raise UserError(f'{suite.path}: bag {entry.name}: {e}') from None
    return PreparedBag(entry, Path(bag), rig, rig_file, entry.params or default_params())


def replay_and_score(p: PreparedBag, out: Path, params: Path = None):
    """One lockstep replay of the graph over the bag, scored: (figures, evaluator metrics).
    Writes `out`/output (the recorded bag), odometry.tum, report.md and the plots.
    `params`: a params file instead of the bag entry's."""
    from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
    from multicam_ego_motion.evaluation.trajectory_io import load_tum, read_bag_topic, save_tum
    from multicam_ego_motion.replay import run_graph
    e = p.entry
    out.mkdir(parents=True, exist_ok=True)
    rig_file = p.rig_file
    if rig_file is None:
        rig_file = out / 'rig.yaml'
        p.rig.save(rig_file)
    log = []
    try:
        g = run_graph(p.bag, out, p.rig, rig_file, params or p.params, e.workers, lockstep=True,
                      use_wheel=not e.no_wheel, duration=e.duration, logger=log.append)
    finally:
        (out / 'coordinator.log').write_text(''.join(line + '\n' for line in log))
    if g.counts.get('/odom', 0) == 0:
        raise UserError(f'the graph published no /odom (see {out / "logs"})')
    save_tum(read_bag_topic(out / 'output', '/odom'), out / 'odometry.tum')
    est = load_tum(out / 'odometry.tum')
    ref = read_bag_topic(p.bag, e.ground_truth_topic)
    metrics = evaluate_trajectories(ref, est, out_dir=out)
    return figures_from(metrics, g.playback.published_at.keys(), est.stamps), metrics


def replay_repeats(p: PreparedBag, result: BagResult, label: str):
    """A bag entry's `repeat`: one replay per value of its quarter parameter, each in its own
    folder with its own params file; the bag's figures are their mean (mean_of_replays)."""
    from multicam_ego_motion.params_file import with_node_param
    rep = p.entry.repeat
    runs, metrics = [], {}
    for value, name in zip(rep.values, rep.labels()):
        out = result.out_dir / name
        out.mkdir(parents=True, exist_ok=True)
        params = with_node_param(p.params, 'quarter_node', rep.parameter, value, out / 'params.yaml')
        figures, metrics[name] = replay_and_score(p, out, params)
        runs.append(figures)
        result.replays.append(name)
        print(f'check: {label}: {name}: ATE {FIGURES["ate_pct"].format(figures["ate_pct"])} %, final drift '
              f'{FIGURES["final_drift_pct"].format(figures["final_drift_pct"])} %, /odom for '
              f'{figures["frames_with_odometry"]} of {figures["frames"]} frames', flush=True)
    return mean_of_replays(runs), metrics


def check_bag(p: PreparedBag, out: Path, baseline, label: str) -> BagResult:
    e = p.entry
    result = BagResult(e.name, str(p.bag), out / e.name,
                       started=datetime.now(timezone.utc).isoformat(timespec='seconds'))
    how = f'lockstep, {e.workers} workers' + (', no wheel' if e.no_wheel else '') \
        + (f', first {e.duration:g} s' if e.duration else '') \
        + (f', {len(e.repeat.values)} times: {", ".join(e.repeat.labels())}, judged by the mean'
           if e.repeat else '')
    print(f'check: {label}: replaying {p.bag} ({how})', flush=True)
    t0 = time.monotonic()
    try:
        if e.repeat:
            result.figures, result.metrics = replay_repeats(p, result, label)
        else:
            result.figures, result.metrics = replay_and_score(p, result.out_dir)
    except KeyboardInterrupt:     # a signal (interrupt.Interrupted): the command ends
        raise
    except UserError as err:
        result.error = str(err)
    except Exception:             # a CI run reports it as this bag's error and goes on
        result.error = traceback.format_exc()
    result.seconds = time.monotonic() - t0
    if result.error is not None:
        print(f'check: {label}: replay failed: {result.error.strip().splitlines()[-1]}', flush=True)
        return result
    result.checks = limit_checks(e.name, result.figures, e.limits)
    if baseline is not None and e.uses_baseline:
        result.checks += baseline_checks(e.name, result.figures, baseline.get(e.name),
                                         e.baseline_tolerance_pct, e.limits)
    failed = result.failed_checks
    print(f'check: {label}: {result.figures.get("frames", "?")} frames in {result.seconds:.1f} s, '
          + (f'{len(failed)} of {len(result.checks)} checks FAIL ({", ".join(c.name for c in failed)})'
             if failed else f'{len(result.checks)} checks pass'), flush=True)
    return result


def run(args) -> int:
    from multicam_ego_motion.ros_plumbing import dds_transport, ros_domain

    suite = load_suite(args.suite)
    entries = suite.bags
    if args.only:
        unknown = [n for n in args.only if n not in {e.name for e in entries}]
        if unknown:
            raise UserError(f'--only: {", ".join(unknown)} not in {suite.path} '
                            f'(its bags: {", ".join(e.name for e in entries)})')
        entries = [e for e in entries if e.name in args.only]
    baseline_path = Path(args.baseline).resolve() if args.baseline else suite.baseline
    baseline = kept = None
    if args.update_baseline:
        if baseline_path is None:
            raise UserError(f'--update-baseline: where to? give --baseline FILE or "baseline:" in {suite.path}')
        kept = load_baseline(baseline_path) if baseline_path.exists() else {}
    else:
        wanting = [e.name for e in entries if e.uses_baseline]
        if wanting and baseline_path is None:
            raise UserError(f'{suite.path}: {", ".join(wanting)} compare with a baseline '
                            '(baseline_tolerance_pct): give --baseline FILE or "baseline:" in the suite')
        if wanting:
            baseline = load_baseline(baseline_path)
        elif args.baseline:
            print(f'check: no bag of {suite.path} has baseline_tolerance_pct: '
                  f'nothing is compared with {baseline_path}', flush=True)

    out = Path(args.out)
    check_out(out)
    cache = Path(args.bags_cache) if args.bags_cache else default_cache()
    ros_domain.isolate()
    dds_transport.use_graph_profile()
    labels = [f'[{i + 1}/{len(entries)}] {e.name}' for i, e in enumerate(entries)]
    # Every input error before the first replay: a bad bag late in the suite must not cost
    # the replays before it.
    prepared = [prepare(e, suite, cache, lb) for e, lb in zip(entries, labels)]
    prepare_out(out, [e.name for e in entries])
    results = [check_bag(p, out, baseline, lb) for p, lb in zip(prepared, labels)]

    written = None
    if args.update_baseline:
        names = {e.name for e in suite.bags}      # with --only, the others' stay too
        keep = {k: v for k, v in kept.items() if k in names}
        write_baseline(baseline_path, suite.path,
                       {r.name: r.figures for r in results if r.error is None}, keep)
        written = baseline_path
    write_reports(out, suite, results, baseline_path if baseline is not None else None, written)
    print()
    print('\n'.join(markdown_table(table_rows(results))))
    print(f'\ncheck: wrote {out}/summary.md, junit.xml, results.json and per-bag plots')
    if written:
        print(f'check: baseline written: {written}')
    print(verdict_line(results), flush=True)
    return 0 if all(r.passed for r in results) else 1
