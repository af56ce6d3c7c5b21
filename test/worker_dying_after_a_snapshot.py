"""A replay worker (`python -m multicam_ego_motion.coordinator.worker`) that kills itself
right after it saved the general arbiter's state of frame DIE_AFTER_SNAPSHOT, for
test_faults_processes: the frame's /odom is out and a restore will not fuse it again, so
anything of the frame still held in this process is lost. Only the first worker to get
there dies (a marker file next to the snapshots), not the one that restores the arbiter."""
import os
import signal
import sys
from pathlib import Path

from multicam_ego_motion.coordinator import worker

NTH = int(os.environ['DIE_AFTER_SNAPSHOT'])
snapshot = worker.Worker.snapshot


def dying_snapshot(self, key, node):
    snapshot(self, key, node)
    marker = Path(os.environ['DIE_MARKER'])
    if key == 'general_arbiter' and self.frames_done[key] == NTH and not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)


worker.Worker.snapshot = dying_snapshot
sys.exit(worker.main())
