"""Python's garbage collection in a worker's idle time instead of in the middle of a frame.

Measured on the default bag (sequential pipeline, gc callbacks): a full collection walked the
~80 000 objects of the imported libraries (numpy, scipy, rclpy, OpenCV) and paused the
pipeline for up to 58 ms, twice per run; in a worker such a pause lands on one frame's
latency. So the objects that exist once the worker has imported everything are frozen (never
walked again: they live as long as the process), automatic collection is off, and the worker
collects what is due whenever it finds nothing to do (worker.py), by Python's thresholds
(a full collection every tenth middle one: Python also waits for the long-lived objects to
grow by a quarter, a saving that matters less in idle time). A worker that is never idle
(overloaded) still collects once the young generation is far past its threshold: memory
stays bounded.
"""
import gc

# Collect even while busy once the youngest generation holds this many times its threshold.
BUSY_FACTOR = 20


class IdleCollector:
    def __init__(self):
        self.thresholds = gc.get_threshold()
        gc.collect()
        gc.freeze()
        gc.disable()

    def generation_due(self):
        """The oldest generation whose threshold is reached (Python's own rule), or None."""
        counts = gc.get_count()
        if counts[0] < self.thresholds[0]:
            return None
        gen = 0
        while gen < 2 and counts[gen + 1] >= self.thresholds[gen + 1]:
            gen += 1
        return gen

    def due(self) -> bool:
        return self.generation_due() is not None

    def collect_idle(self):
        gen = self.generation_due()
        if gen is not None:
            gc.collect(gen)

    def collect_if_overdue(self):
        """While busy: only when far past due (a worker that never gets idle)."""
        if gc.get_count()[0] >= BUSY_FACTOR * self.thresholds[0]:
            gc.collect(self.generation_due())

    def close(self):
        gc.unfreeze()
        gc.enable()
