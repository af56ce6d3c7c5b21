"""Baseline files: the figures of an earlier run, per bag, that a suite compares against.

A baseline is JSON (or YAML when its name ends in .yaml / .yml) of the form
`{"bags": {NAME: {"figures": {FIGURE: value, ...}}, ...}}`; a run's results.json has that
form, so any earlier run's results can serve as the baseline. `--update-baseline` writes
one from the run just made.
"""
import json
from pathlib import Path
from typing import Dict, Optional

from multicam_ego_motion.errors import UserError

YAML_SUFFIXES = ('.yaml', '.yml')


def _parse(path: Path, text: str):
    if path.suffix in YAML_SUFFIXES:
        import yaml
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise UserError(f'baseline {path}: not valid YAML ({e})') from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise UserError(f'baseline {path}: not valid JSON ({e})') from None


def load_baseline(path) -> Dict[str, Dict[str, Optional[float]]]:
    """{bag name: {figure: value}}."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f'baseline file not found: {path} (write one with --update-baseline)')
    doc = _parse(path, path.read_text())
    bags = doc.get('bags') if isinstance(doc, dict) else None
    if not isinstance(bags, dict):
        raise UserError(f'baseline {path}: expected a mapping "bags" of bag name to its figures')
    out = {}
    for name, body in bags.items():
        figures = body.get('figures') if isinstance(body, dict) else None
        if not isinstance(figures, dict):
            raise UserError(f'baseline {path}: bag {name}: expected "figures", a mapping of figure to value')
        for key, value in figures.items():
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
                raise UserError(f'baseline {path}: bag {name}: {key}: expected a number, got {value!r}')
        out[str(name)] = figures
    return out


def write_baseline(path, suite_path, figures_by_bag: Dict[str, dict], keep: Optional[dict] = None):
    """Write the figures of the bags that replayed; `keep` (the previous baseline's bags)
    stays for the bags that did not (a failed replay does not erase their baseline)."""
    path = Path(path)
    bags = {name: {'figures': figs} for name, figs in (keep or {}).items()}
    bags.update({name: {'figures': figs} for name, figs in figures_by_bag.items()})
    doc = {'suite': str(suite_path), 'bags': bags}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + '.tmp')
    if path.suffix in YAML_SUFFIXES:
        import yaml
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
    else:
        tmp.write_text(json.dumps(doc, indent=2) + '\n')
    tmp.replace(path)
