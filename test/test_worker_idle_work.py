"""A worker's queue of idle work (worker.py), with a real rclpy node but no graph."""
from multicam_ego_motion.coordinator.worker import Worker


class Quarter:
    def __init__(self):
        self.ran = 0

    def work_ahead(self):
        self.ran += 1


def test_a_node_that_offers_work_again_is_queued_once_in_first_offer_order(rclpy_context):
    worker = Worker(0, conn=None, params_file=None)
    try:
        a, b = Quarter(), Quarter()
        for node in (a, b, a, a, b):        # image, fused pose, image, ... with no idle time
            worker.offer_idle_work(node)
        assert worker.idle_work == [a, b]
        worker.idle_work.pop(0).work_ahead()
        worker.offer_idle_work(a)           # done once, offered again: queued again
        assert worker.idle_work == [b, a] and a.ran == 1
    finally:
        worker.gc.close()
        worker.executor.shutdown()
        worker.node.destroy_node()
