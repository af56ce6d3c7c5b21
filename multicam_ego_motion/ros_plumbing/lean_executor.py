"""A single-threaded executor for a worker's nodes that rebuilds its entity lists only when
they change.

Why: rclpy's SingleThreadedExecutor gathers every entity of every node into a new wait set,
in Python, before each wait (contexts entered, filters, a WaitSet object), and wraps every
callback in a Task whose end triggers the executor's guard condition, so each callback costs
one more wait that finds nothing (10-13 waits per frame and worker at M = 2; docs/transport.md
has what that measured to). Here the entity lists and the pointer -> entity maps are built
once per change of the nodes (add_node, remove_node, an entity created or destroyed: rclpy
calls wake() then), a wait only re-adds the cached handles to a reused wait set, and ready
callbacks are called directly.

Scope: what a worker's nodes use (subscriptions, timers, guard conditions, waitables such as
QoS event handlers, services and clients), one thread, no callback groups or coroutine tasks
(a coroutine callback is run to completion at once). Entities are taken when their callback
runs, not when the wait returns, so a callback that destroys another entity of the same batch
(a node detached) makes that one skipped, as in rclpy.

Threads: entities may be created from another thread while one spins (the next wait sees
them), but not destroyed there: unlike rclpy's executor, a wait does not hold a use count on
every handle (that costs ~20 us a wait), so an entity must be destroyed by the spinning
thread, between waits, or after the spinning stopped.
"""
import inspect
import threading
from typing import Callable, List, Optional

from rclpy.executors import ExternalShutdownException, ShutdownException
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerGuardCondition
from rclpy.subscription import Subscription
from rclpy.utilities import get_default_context, timeout_sec_to_nsec

try:
    from rclpy.exceptions import InvalidHandle
except ImportError:             # older rclpy
    from rclpy.handle import InvalidHandle      # type: ignore


def _run(result):
    """A callback that is a coroutine function returned a coroutine: run it to completion
    (single thread: it has nothing to wait for but itself)."""
    if inspect.iscoroutine(result):
        try:
            while True:
                result.send(None)
        except StopIteration as done:
            return done.value
    return result


class LeanExecutor:
    def __init__(self, context=None):
        self._context = context or get_default_context()
        self._nodes: list = []
        self._lock = threading.Lock()
        self._dirty = True
        self._is_shutdown = False
        # Wakes a blocking wait when the entities change from another thread, or on shutdown.
        self._guard = GuardCondition(callback=None, callback_group=None, context=self._context)
        self._sigint_gc = SignalHandlerGuardCondition(self._context)
        self._context.on_shutdown(self.wake)
        self._wait_set = None

    # ----- the node set (the parts of rclpy's Executor API that nodes call) ----------------
    @property
    def context(self):
        return self._context

    def add_node(self, node) -> bool:
        with self._lock:
            if any(n is node for n in self._nodes):
                return False
            self._nodes.append(node)
            self._dirty = True
        node.executor = self        # (rclpy's setter calls add_node again: a no-op now)
        self._guard.trigger()
        return True

    def remove_node(self, node) -> None:
        with self._lock:
            kept = [n for n in self._nodes if n is not node]
            if len(kept) == len(self._nodes):
                return
            self._nodes = kept
            self._dirty = True
        self._guard.trigger()

    def get_nodes(self) -> list:
        with self._lock:
            return list(self._nodes)

    def wake(self) -> None:
        """An entity was created or destroyed (rclpy's nodes call this), or shutdown."""
        self._dirty = True
        if self._guard is not None:
            self._guard.trigger()

    def shutdown(self, timeout_sec: Optional[float] = None) -> bool:
        self._is_shutdown = True
        if self._guard is not None:
            self._guard.trigger()
        with self._lock:
            self._nodes = []
        self._wait_set = None
        for gc in (self._guard, self._sigint_gc):
            if gc is not None:
                gc.destroy()
        self._guard = self._sigint_gc = None
        return True

    # ----- waiting --------------------------------------------------------------------------
    def _rebuild(self):
        with self._lock:
            nodes = list(self._nodes)
            self._dirty = False
        subs, timers, guards, waitables, services, clients = [], [], [], [], [], []
        for node in nodes:
            subs += node.subscriptions
            timers += node.timers
            guards += node.guards
            waitables += node.waitables
            services += node.services
            clients += node.clients
        guards = [g for g in guards] + [self._guard, self._sigint_gc]
        self._subs = {s.handle.pointer: s for s in subs}
        self._timers = {t.handle.pointer: t for t in timers}
        self._guards = {g.handle.pointer: g for g in guards}
        self._services = {s.handle.pointer: s for s in services}
        self._clients = {c.handle.pointer: c for c in clients}
        self._waitables = waitables
        # creation order within each kind, node by node (rclpy takes them the same way)
        self._order = (list(self._subs.values()), list(self._timers.values()),
                       list(self._guards.values()), list(self._services.values()),
                       list(self._clients.values()))
        events = 0
        extra = [0, 0, 0, 0, 0]
        for w in waitables:
            n = w.get_num_entities()
            extra[0] += n.num_subscriptions
            extra[1] += n.num_guard_conditions
            extra[2] += n.num_timers
            extra[3] += n.num_clients
            extra[4] += n.num_services
            events += n.num_events
        self._wait_set = _rclpy.WaitSet(
            len(self._subs) + extra[0], len(self._guards) + extra[1], len(self._timers) + extra[2],
            len(self._clients) + extra[3], len(self._services) + extra[4], events,
            self._context.handle)

    def wait_ready(self, timeout_sec: Optional[float] = None) -> List[Callable[[], None]]:
        """Wait up to timeout_sec (None: forever, 0: just look) and return the ready
        callbacks, in the order to call them; empty when the wait timed out."""
        if self._is_shutdown:
            raise ShutdownException()
        if self._dirty or self._wait_set is None:
            self._rebuild()
        ws = self._wait_set
        subs, timers, guards, services, clients = self._order
        with self._context.handle:
            ws.clear_entities()
            for s in subs:
                ws.add_subscription(s.handle)
            for t in timers:
                ws.add_timer(t.handle)
            for g in guards:
                ws.add_guard_condition(g.handle)
            for s in services:
                ws.add_service(s.handle)
            for c in clients:
                ws.add_client(c.handle)
            for w in self._waitables:
                w.add_to_wait_set(ws)
            ws.wait(timeout_sec_to_nsec(timeout_sec))
        if self._is_shutdown:
            raise ShutdownException()
        if not self._context.ok():
            raise ExternalShutdownException()

        ready: List[Callable[[], None]] = []
        for w in self._waitables:
            if w.is_ready(ws):
                ready.append(lambda w=w: _run(w.execute(w.take_data())))
        for p in ws.get_ready_entities('timer'):
            t = self._timers.get(p)
            if t is not None:
                ready.append(lambda t=t: self._call_timer(t))
        for p in ws.get_ready_entities('subscription'):
            s = self._subs.get(p)
            if s is not None:
                ready.append(lambda s=s: self._call_subscription(s))
        for p in ws.get_ready_entities('guard_condition'):
            g = self._guards.get(p)
            if g is not None and g.callback is not None:
                ready.append(lambda g=g: _run(g.callback()))
        for p in ws.get_ready_entities('service'):
            s = self._services.get(p)
            if s is not None:
                ready.append(lambda s=s: self._call_service(s))
        for p in ws.get_ready_entities('client'):
            c = self._clients.get(p)
            if c is not None:
                ready.append(lambda c=c: self._call_client(c))
        return ready

    def spin_once(self, timeout_sec: Optional[float] = None) -> None:
        """Wait once (as wait_ready) and call what is ready."""
        for call in self.wait_ready(timeout_sec):
            call()

    # ----- taking and calling ---------------------------------------------------------------
    @staticmethod
    def _call_timer(t):
        try:
            with t.handle:
                # rcl reports cancelled timers ready; rclpy checks the same way
                if not t.handle.is_timer_ready():
                    return
                t.handle.call_timer()
        except InvalidHandle:           # destroyed by an earlier callback of this batch
            return
        _run(t.callback())

    @staticmethod
    def _call_subscription(s):
        try:
            with s.handle:
                info = s.handle.take_message(s.msg_type, s.raw)
        except InvalidHandle:
            return
        if info is None:
            return
        if s._callback_type is Subscription.CallbackType.MessageOnly:
            _run(s.callback(info[0]))
        else:
            _run(s.callback(*info))

    @staticmethod
    def _call_service(s):
        try:
            with s.handle:
                request, header = s.handle.service_take_request(s.srv_type.Request)
        except InvalidHandle:
            return
        if header is None:
            return
        s.send_response(_run(s.callback(request, s.srv_type.Response())), header)

    def _call_client(self, c):
        try:
            with c.handle:
                header, response = c.handle.take_response(c.srv_type.Response)
        except InvalidHandle:
            return
        if header is None:
            return
        try:
            future = c.get_pending_request(header.request_id.sequence_number)
        except KeyError:                # the request was cancelled
            return
        future.set_result(response)
