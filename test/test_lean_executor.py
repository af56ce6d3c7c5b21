"""The workers' executor (ros_plumbing/lean_executor.py) over real rclpy entities and DDS:
subscriptions, timers and guard conditions are called; entities created, destroyed, nodes
added and removed are seen by the next wait; an entity destroyed by an earlier callback of
the same batch is skipped."""
import time

import pytest
import rclpy
from std_msgs.msg import Int64

from multicam_ego_motion.ros_plumbing.lean_executor import LeanExecutor
from multicam_ego_motion.ros_plumbing.qos import RELIABLE


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def spin_until(ex, predicate, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        for call in ex.wait_ready(0.05):
            call()
    return predicate()


def test_subscriptions_timers_guards_and_changes(context):
    ex = LeanExecutor(context=context)
    pub_node = rclpy.create_node('lean_pub', context=context)
    sub_node = rclpy.create_node('lean_sub', context=context)
    ex.add_node(pub_node)
    ex.add_node(sub_node)
    assert sub_node.executor is ex and ex.add_node(sub_node) is False
    got, ticks, guarded = [], [], []
    sub = sub_node.create_subscription(Int64, '/lean_test', lambda m: got.append(m.data), RELIABLE)
    pub = pub_node.create_publisher(Int64, '/lean_test', RELIABLE)
    assert spin_until(ex, lambda: pub.get_subscription_count() == 1)
    for i in range(5):
        pub.publish(Int64(data=i))
    assert spin_until(ex, lambda: len(got) == 5)
    assert got == [0, 1, 2, 3, 4]

    timer = sub_node.create_timer(0.01, lambda: ticks.append(1))
    assert spin_until(ex, lambda: len(ticks) >= 3)
    timer.cancel()
    n = len(ticks)
    for _ in range(10):
        for call in ex.wait_ready(0.02):
            call()
    assert len(ticks) == n, 'a cancelled timer still fired'

    gc = sub_node.create_guard_condition(lambda: guarded.append(1))
    gc.trigger()
    assert spin_until(ex, lambda: guarded == [1])

    # A node removed from the executor is no longer served.
    ex.remove_node(sub_node)
    pub.publish(Int64(data=99))
    for _ in range(10):
        for call in ex.wait_ready(0.02):
            call()
    assert 99 not in got
    ex.add_node(sub_node)
    assert spin_until(ex, lambda: 99 in got)

    # Destroyed by an earlier callback of the same batch: skipped, not an error.
    other = []
    sub2 = sub_node.create_subscription(Int64, '/lean_test2', lambda m: other.append(m.data), RELIABLE)
    pub2 = pub_node.create_publisher(Int64, '/lean_test2', RELIABLE)
    assert spin_until(ex, lambda: pub2.get_subscription_count() == 1)
    killer = pub_node.create_guard_condition(lambda: sub_node.destroy_subscription(sub2))
    pub2.publish(Int64(data=1))
    time.sleep(0.2)
    killer.trigger()
    calls = ex.wait_ready(1.0)
    # (both may be ready at once; whatever order, nothing raises)
    for call in calls:
        call()
    for _ in range(5):
        for call in ex.wait_ready(0.02):
            call()
    assert sub2 not in list(sub_node.subscriptions)
    ex.shutdown()
    sub_node.destroy_node()
    pub_node.destroy_node()
    del sub


def test_wait_times_out_empty(context):
    ex = LeanExecutor(context=context)
    node = rclpy.create_node('lean_idle', context=context)
    ex.add_node(node)
    assert ex.wait_ready(0.0) == []
    assert ex.wait_ready(0.05) == []
    ex.shutdown()
    node.destroy_node()


RACE = r'''
import threading, rclpy
from std_msgs.msg import Int64
from multicam_ego_motion.ros_plumbing.lean_executor import LeanExecutor
from multicam_ego_motion.ros_plumbing.lean_node import LeanNode
rclpy.init()
node = LeanNode('lean_race')
ex = LeanExecutor()
ex.add_node(node)
stop = threading.Event()
got = []
def spin():
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.01)
t = threading.Thread(target=spin)
t.start()
pubs = []
for i in range(150):
    node.create_subscription(Int64, f'/lean_race/s{i}', got.append, 10)
    pubs.append(node.create_publisher(Int64, f'/lean_race/s{i}', 10))
stop.set()
ex.wake()
t.join()
ex.shutdown()
n = len(list(node.waitables))
node.destroy_node()
rclpy.shutdown()
print('waitables', n)
'''


def test_entities_created_while_another_thread_spins(tmp_path):
    """The replay process creates its recorder's subscriptions and its player's publishers
    on the main thread while a thread spins the LeanExecutor. A LeanNode's entities have no
    QoS event handlers at all (rclpy's defaults created, then destroyed under the other
    thread's wait, crashed the process with SIGSEGV)."""
    import subprocess
    import sys
    script = tmp_path / 'race.py'
    script.write_text(RACE)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    assert r.stdout.split() == ['waitables', '0']
