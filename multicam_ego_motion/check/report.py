"""What a check run writes: the table (printed and in summary.md), junit.xml, results.json.

JUnit: one <testsuite> per bag, one <testcase> per bag x figure (classname
`<suite>.<bag>`, name the figure, or `<figure> vs baseline`); a figure out of bounds is a
<failure> whose message names the bag and the figure, a bag that could not be replayed an
<error> (testcase `replay`), a bag missing from the baseline <skipped>. Times are seconds: a
bag's suite time is its replay and scoring, spread evenly over its test cases.
"""
import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import List, Optional

from multicam_ego_motion.check.figures import Check

TABLE_HEAD = ('bag', 'figure', 'value', 'limit / baseline', 'result')


@dataclass
class BagResult:
    name: str
    bag: str                         # the bag folder replayed
    out_dir: Path                    # its replay and plots
    seconds: float = 0.0
    figures: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)      # the evaluator's, all of them
    checks: List[Check] = field(default_factory=list)
    error: Optional[str] = None      # the replay failed: why
    started: str = ''                # ISO time
    replays: List[str] = field(default_factory=list)  # a `repeat`: each replay's folder in out_dir

    @property
    def failed_checks(self) -> List[Check]:
        return [c for c in self.checks if not c.passed]

    @property
    def passed(self) -> bool:
        return self.error is None and not self.failed_checks

    def plots(self) -> List[str]:
        """The evaluator's figures, relative to the check's output folder."""
        return [f'{self.name}/{d}{p}' for d in ([f'{r}/' for r in self.replays] or [''])
                for p in ('trajectory.png', 'error_over_distance.png') if (self.out_dir / d / p).exists()]


def verdict(check: Check) -> str:
    return 'skipped' if check.skipped else ('pass' if check.passed else 'FAIL')


def table_rows(results: List[BagResult]):
    rows = []
    for r in results:
        if r.error is not None:
            rows.append((r.name, 'replay', 'error', r.error.splitlines()[0] if r.error else '', 'ERROR'))
            continue
        for c in r.checks:
            value = '' if c.skipped and c.figure == 'figures' else c.spec.format(c.value)
            rows.append((r.name, c.name, value, c.condition(), verdict(c)))
    return rows


def markdown_table(rows, head=TABLE_HEAD) -> List[str]:
    """A markdown table with padded columns (readable printed, too)."""
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    line = lambda cells: '| ' + ' | '.join(str(c).ljust(w) for c, w in zip(cells, widths)) + ' |'  # noqa: E731
    return [line(head), '|' + '|'.join('-' * (w + 2) for w in widths) + '|'] + [line(r) for r in rows]


def failure_names(results: List[BagResult]) -> List[str]:
    """'loop ate_pct', 'corridor replay', ...: each failing bag and figure."""
    out = []
    for r in results:
        if r.error is not None:
            out.append(f'{r.name} replay')
        out += [f'{r.name} {c.name}' for c in r.failed_checks]
    return out


def verdict_line(results: List[BagResult]) -> str:
    """The last line: every failing bag and figure with its value and bound, or all pass."""
    n = sum(len(r.checks) for r in results if r.error is None) + sum(r.error is not None for r in results)
    failed = []
    for r in results:
        if r.error is not None:
            failed.append(f'{r.name} replay (error)')
        failed += [f'{r.name} {c.name} {c.spec.format(c.value)} (allowed {c.condition()})'
                   for c in r.failed_checks]
    if not failed:
        return f'check: all {n} checks of {len(results)} bags pass'
    return f'check: REGRESSION in {len(failed)} of {n} checks: ' + '; '.join(failed)


def summary_markdown(suite_name: str, suite_path, results: List[BagResult], baseline=None,
                     baseline_written=None) -> str:
    lines = [f'# ego-motion check: {suite_name}', '',
             f'Suite `{suite_path}`' + (f', baseline `{baseline}`' if baseline else '') + '.', '']
    lines += markdown_table(table_rows(results))
    lines += ['', verdict_line(results).replace('check: ', '', 1), '']
    if baseline_written:
        lines += [f'Baseline written: `{baseline_written}`.', '']
    lines += ['## Bags', '']
    for r in results:
        f = r.figures
        about = (f'{f["frames"]} frames, ' if 'frames' in f else '') \
            + (f'{f["path_length_m"]:.1f} m, ' if 'path_length_m' in f else '') + f'{r.seconds:.0f} s'
        plots = ', '.join(f'[{Path(p).stem}]({p})' for p in r.plots())
        lines.append(f'- **{r.name}** ({"pass" if r.passed else "FAIL"}): `{r.bag}`, {about}'
                     + (f'; plots: {plots}, [report]({r.name}/report.md)' if plots else '')
                     + (f'; error: {r.error.splitlines()[0]}' if r.error else ''))
    return '\n'.join(lines) + '\n'


def _seconds(x: float) -> str:
    return f'{x:.3f}'


def junit_xml(suite_name: str, results: List[BagResult]) -> bytes:
    root = ET.Element('testsuites', name=f'ego-motion check {suite_name}')
    totals = {'tests': 0, 'failures': 0, 'errors': 0, 'skipped': 0}
    for r in results:
        ts = ET.SubElement(root, 'testsuite', name=r.name, timestamp=r.started or '',
                           time=_seconds(r.seconds))
        classname = f'{suite_name}.{r.name}'
        counts = {'tests': 0, 'failures': 0, 'errors': 0, 'skipped': 0}
        if r.error is not None:
            tc = ET.SubElement(ts, 'testcase', classname=classname, name='replay', time=_seconds(r.seconds))
            err = ET.SubElement(tc, 'error', message=f'{r.name}: replay failed: {r.error.splitlines()[0]}',
                                type='replay')
            err.text = r.error
            counts['tests'] += 1
            counts['errors'] += 1
        share = r.seconds / len(r.checks) if r.checks and r.error is None else 0.0
        for c in (r.checks if r.error is None else []):
            tc = ET.SubElement(ts, 'testcase', classname=classname, name=c.name, time=_seconds(share))
            counts['tests'] += 1
            if c.skipped:
                ET.SubElement(tc, 'skipped', message=c.message())
                counts['skipped'] += 1
            elif not c.passed:
                fail = ET.SubElement(tc, 'failure', message=c.message(), type='regression')
                fail.text = (f'bag {r.name} ({r.bag}), figure {c.figure} ({c.spec.label}): '
                             f'{c.spec.format(c.value)}, allowed {c.condition()}.\n'
                             f'Plots: {", ".join(r.plots()) or "none"}')
                counts['failures'] += 1
        if r.plots():
            ET.SubElement(ts, 'system-out').text = 'plots: ' + ', '.join(r.plots())
        for k, v in counts.items():
            ts.set(k, str(v))
            totals[k] += v
    for k, v in totals.items():
        root.set(k, str(v))
    root.set('time', _seconds(sum(r.seconds for r in results)))
    ET.indent(root)
    return ET.tostring(root, encoding='utf-8', xml_declaration=True) + b'\n'


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def results_json(suite_path, results: List[BagResult], baseline=None) -> str:
    doc = {
        'suite': str(suite_path),
        'baseline': str(baseline) if baseline else None,
        'written': datetime.now(timezone.utc).isoformat(timespec='seconds'),
        'passed': all(r.passed for r in results),
        'failures': failure_names(results),
        'bags': {r.name: {'bag': r.bag, 'passed': r.passed, 'seconds': round(r.seconds, 3),
                          'error': r.error, 'figures': r.figures, 'checks': [c.to_json() for c in r.checks],
                          'plots': r.plots(), 'metrics': r.metrics}
                 for r in results},
    }
    return json.dumps(_json_safe(doc), indent=2) + '\n'


def write_reports(out: Path, suite, results: List[BagResult], baseline=None, baseline_written=None):
    """results.json, summary.md and junit.xml into `out`."""
    (out / 'results.json').write_text(results_json(suite.path, results, baseline))
    (out / 'summary.md').write_text(summary_markdown(suite.name, suite.path, results, baseline,
                                                     baseline_written))
    (out / 'junit.xml').write_bytes(junit_xml(suite.name, results))
