"""Bags a suite describes by `generate:` (a scenario) or `import_kitti:` (a KITTI sequence),
made once into a cache folder.

A cached bag's folder name says its settings and ends with a fingerprint of the renderer's
and bag writer's source, so a change to either renders the bag anew instead of reusing a
stale one. A bag is rendered into a temporary folder beside its place and renamed into it
when complete: an interrupted render or two checks rendering the same bag at once never
leave a half-written bag under the cached name.
"""
import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

PACKAGE = Path(__file__).resolve().parent.parent
# What the rendered bytes depend on.
RENDER_SOURCES = ('scenarios', 'bag/rig_bag_writer.py', 'bag/rosbag2_writer.py', 'geometry/rig.py',
                  'geometry/camera_intrinsics.py')


@dataclass(frozen=True)
class GenerateSpec:
    scenario: str
    seed: int = 0
    duration: float = 30.0
    rate: float = 30.0
    width: int = 640
    height: int = 480
    fx: Optional[float] = None
    k1: float = 0.0
    cameras: int = 4

    def describe(self) -> str:
        return (f'{self.scenario} seed {self.seed}, {self.duration:g} s at {self.rate:g} Hz, '
                f'{self.width}x{self.height}' + (f', fx {self.fx:g}' if self.fx else ''))

    def folder_name(self) -> str:
        name = (f'{self.scenario}_s{self.seed}_{self.duration:g}s_{self.rate:g}hz_'
                f'{self.width}x{self.height}')
        if self.fx is not None:
            name += f'_fx{self.fx:g}'
        if self.k1:
            name += f'_k{self.k1:g}'
        if self.cameras != 4:
            name += f'_{self.cameras}cam'
        return f'{name}_{renderer_fingerprint()}'


@dataclass(frozen=True)
class KittiSpec:
    """A KITTI sequence folder imported as `ego-motion import-kitti` does (kitti_import)."""
    folder: Path
    every: int = 1
    no_stereo: bool = False
    halves: bool = False

    def describe(self) -> str:
        opts = [f'every {self.every}'] * (self.every > 1) + ['no stereo'] * self.no_stereo \
            + ['halves'] * self.halves
        return f'KITTI {self.folder}' + (f' ({", ".join(opts)})' if opts else '')

    def folder_name(self) -> str:
        name = f'kitti_{self.folder.name}_every{self.every}' + '_nostereo' * self.no_stereo \
            + '_halves' * self.halves
        key = hashlib.sha256(str(self.folder.resolve()).encode()
                             + (PACKAGE / 'kitti_import.py').read_bytes()).hexdigest()[:6]
        return f'{name}_{key}{renderer_fingerprint()}'


def default_cache() -> Path:
    base = os.environ.get('XDG_CACHE_HOME') or Path.home() / '.cache'
    return Path(base) / 'multicam_ego_motion' / 'bags'


_fingerprint = None


def renderer_fingerprint() -> str:
    """8 hex digits of the renderer's and writer's source."""
    global _fingerprint
    if _fingerprint is None:
        h = hashlib.sha256()
        files = []
        for rel in RENDER_SOURCES:
            p = PACKAGE / rel
            files += sorted(p.glob('*.py')) if p.is_dir() else [p]
        for f in files:
            h.update(f.relative_to(PACKAGE).as_posix().encode() + b'\0' + f.read_bytes())
        _fingerprint = h.hexdigest()[:8]
    return _fingerprint


def cached_bag(cache: Path, spec) -> Path:
    return Path(cache) / spec.folder_name()


def is_complete(bag: Path) -> bool:
    return (bag / 'metadata.yaml').exists()


def ensure_generated(cache: Path, spec) -> Path:
    """The cached bag of `spec` (GenerateSpec or KittiSpec), made first when missing."""
    bag = cached_bag(cache, spec)
    if is_complete(bag):
        return bag
    bag.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f'.{bag.name}.', dir=bag.parent))
    try:
        if isinstance(spec, KittiSpec):
            from multicam_ego_motion.kitti_import import import_kitti
            import_kitti(spec.folder, tmp / 'bag', progress=False, every=spec.every,
                         stereo=not spec.no_stereo, halves=spec.halves)
        else:
            from multicam_ego_motion.scenarios.generator import generate
            generate(spec.scenario, str(tmp / 'bag'), spec.seed, spec.duration, spec.rate, spec.width,
                     spec.height, spec.fx, spec.k1, spec.cameras, None, 'zstd', progress=False)
        try:
            os.rename(tmp / 'bag', bag)
        except OSError:
            if not is_complete(bag):    # not another check's complete copy: a real error
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return bag
