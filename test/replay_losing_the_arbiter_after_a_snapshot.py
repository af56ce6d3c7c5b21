"""`ego-motion replay ...` whose workers are test/worker_dying_after_a_snapshot.py: the
worker hosting the general arbiter dies right after saving its state of frame
DIE_AFTER_SNAPSHOT (for test_faults_processes)."""
import sys

from multicam_ego_motion import cli
from multicam_ego_motion.coordinator import coordinator

coordinator.WORKER_MODULE = 'worker_dying_after_a_snapshot'     # test/ is on PYTHONPATH
sys.exit(cli.main(sys.argv[1:]))
