"""A node's last few outputs by stamp, to send again when an input it already used comes
again: the player re-publishes the frames in flight after a worker restart, and the nodes
that had them already drop the copies. Their outputs had gone to the restarted worker's
nodes, which lost them; without a second copy those waited out a sync timeout (10 s in
lockstep) and fused the frame without the other worker's cameras."""
from collections import OrderedDict
from typing import Optional

# Frames in flight at most (lockstep depth 2) plus a margin.
KEPT = 4


class RecentOutputs:
    def __init__(self, kept: int = KEPT):
        self.kept = int(kept)
        self.items = OrderedDict()

    def add(self, stamp_ns: int, item):
        self.items[int(stamp_ns)] = item
        self.items.move_to_end(int(stamp_ns))
        while len(self.items) > self.kept:
            self.items.popitem(last=False)

    def get(self, stamp_ns: int) -> Optional[object]:
        return self.items.get(int(stamp_ns))

    def get_state(self):
        return list(self.items.items())

    def set_state(self, items):
        self.items = OrderedDict(items or ())
