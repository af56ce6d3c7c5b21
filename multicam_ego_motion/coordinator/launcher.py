"""Start the graph on M worker processes and watch that they live.

The placement comes from coordinator.allocation (the paper's section 3 rules); before any
cost has been measured every quarter is assumed to cost the same.
"""
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from multicam_ego_motion.coordinator.graph_spec import graph_nodes
from multicam_ego_motion.errors import UserError


def static_placement(nodes, workers: int):
    """Whole cameras per worker, then quarters spread, until allocation.py takes over."""
    try:
        from multicam_ego_motion.coordinator.allocation import allocate_nodes
        return allocate_nodes(nodes, workers)
    except ImportError:
        placement = [[] for _ in range(workers)]
        cams = sorted({n.key.split('/')[0] for n in nodes if '/' in n.key})
        for n in nodes:
            cam = n.key.split('/')[0]
            i = cams.index(cam) % workers if cam in cams else workers - 1
            placement[i].append(n)
        return placement


class GraphLauncher:
    def __init__(self, rig, rig_file, params_file=None, workers: int = None, overrides=None,
                 log_dir=None, env=None):
        self.nodes = graph_nodes(rig, str(rig_file), overrides=overrides)
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        self.params_file = str(params_file) if params_file else None
        self.log_dir = Path(log_dir or tempfile.mkdtemp(prefix='ego_motion_workers_'))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        # One BLAS thread per worker: the workers are the parallelism (see cli.py).
        self.env = dict(env if env is not None else os.environ)
        for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
            self.env.setdefault(var, '1')
        self.procs = []
        self.placement = static_placement(self.nodes, self.workers)

    def start(self):
        for i, nodes in enumerate(self.placement):
            if not nodes:
                continue
            spec = {'worker': i, 'params_file': self.params_file, 'nodes': [n.to_dict() for n in nodes]}
            spec_file = self.log_dir / f'worker_{i}.json'
            spec_file.write_text(json.dumps(spec, indent=1))
            log = open(self.log_dir / f'worker_{i}.log', 'w')
            proc = subprocess.Popen([sys.executable, '-m', 'multicam_ego_motion.coordinator.worker',
                                     '--spec', str(spec_file)], stdout=log, stderr=subprocess.STDOUT,
                                    env=self.env)
            self.procs.append((i, proc, log))
        return self

    def check_alive(self):
        """UserError naming the first worker that has exited: what it hosted, and its own
        error line (a worker that fails at start prints one) or the signal that killed it."""
        for i, proc, _ in self.procs:
            if proc.poll() is None:
                continue
            hosted = sorted({n.key.split('/')[0] for n in self.placement[i]})
            code = proc.returncode
            if code < 0:
                name = signal.Signals(-code).name if -code in signal.valid_signals() else f'signal {-code}'
                why = f'was killed by {name}'
            else:
                lines = (self.log_dir / f'worker_{i}.log').read_text().strip().splitlines()
                errors = [l.split(': error: ', 1)[1] for l in lines if ': error: ' in l]
                why = f'exited with code {code}: ' + (errors[-1] if errors else lines[-1] if lines else 'no output')
            raise UserError(f'worker {i} (pid {proc.pid}, hosting {", ".join(hosted)}) {why} '
                            f'(log: {self.log_dir / f"worker_{i}.log"})')

    def stop(self, timeout=10.0):
        for _, proc, _ in self.procs:
            if proc.poll() is None:
                proc.terminate()
        deadline = time.monotonic() + timeout
        for _, proc, log in self.procs:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            log.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
