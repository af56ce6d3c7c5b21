"""Fewer entities in rclpy's wait set: every publisher and subscription brings QoS event
handlers (they log incompatible-QoS warnings), each a waitable that the SingleThreadedExecutor
adds to its wait set, in Python, before every wait. In a process that wakes up dozens of times
a frame they cost more than the callbacks themselves."""
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node


def strip_entity(node, entity):
    """Remove the QoS event handlers of one publisher or subscription of `node`."""
    for h in entity.event_handlers:
        node.remove_waitable(h)
        h.destroy()
    entity.event_handlers = []


def strip_event_handlers(node, keep=lambda topic: topic.endswith(('/image_raw', '/compressed'))):
    """Remove the QoS event handlers of the node's publishers and subscriptions, except on
    `keep` topics (camera images: sensor-data QoS vs a driver's, where the warning helps).
    A worker's 21 nodes: their handlers were most of an idle worker's CPU."""
    for ent in list(node.publishers) + list(node.subscriptions):
        if not keep(ent.topic_name):
            strip_entity(node, ent)


class LeanNode(Node):
    """A node whose publishers and subscriptions come without QoS event handlers: for the
    replay process (player, recorder, coordinator on one node), whose topics are all the
    graph's own and matched on purpose.

    The handlers are never created (rclpy's default callbacks off), not created and then
    removed: that process creates entities on its main thread while another thread spins,
    and a handler destroyed while that thread's wait set held it crashed the process."""

    def create_publisher(self, *args, **kwargs):
        kwargs.setdefault('event_callbacks', PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)

    def create_subscription(self, *args, **kwargs):
        kwargs.setdefault('event_callbacks', SubscriptionEventCallbacks(use_default_callbacks=False))
        return super().create_subscription(*args, **kwargs)


def subscribe_remote(node, subs: dict, names, local, subscribe):
    """Keep `subs` (name -> subscription of `node`) to exactly the `names` not in `local`:
    their estimates a host (worker.py) hands to the node by a call, which saves each a take,
    an executor callback and a reader to write to. subscribe(name) makes one."""
    for name in names:
        sub = subs.get(name)
        if name in local and sub is not None:
            node.destroy_subscription(subs.pop(name))
        elif name not in local and sub is None:
            subs[name] = subscribe(name)
