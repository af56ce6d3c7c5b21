"""Camera arbiter (paper task T_k5): fuses one camera's quarter estimates into /<cam>/pose.

Thin ROS shell over arbiter_node.quarter_fusion (robust, covariance-weighted). Lives in the
camera's namespace; quarters publish /<cam>/q<l>/pose. With `debug_images` it also gathers the
quarters' /<cam>/q<l>/tracks tiles by stamp and publishes them put together as /<cam>/tracks
(sensor_msgs/Image, bgr8: camera_pose_nodes.track_image says why it is done this way).
"""
import time

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import Image

from arbiter_node import quarter_fusion
from arbiter_node.quarter_fusion import fuse_quarters
from arbiter_node.stamp_sync import StampSynchronizer
from camera_pose_nodes.image_conversion import bgr8_message
from multicam_ego_motion.ros_plumbing import diagnostics
from multicam_ego_motion.ros_plumbing.lean_node import subscribe_remote
from multicam_ego_motion.ros_plumbing.node_main import spin_node
from multicam_ego_motion.ros_plumbing.node_parameters import declare_from_table
from multicam_ego_motion.ros_plumbing.pose_messages import estimate_to_msg, msg_to_estimate, ns_to_stamp, stamp_to_ns
from multicam_ego_motion.ros_plumbing.qos import RELIABLE, RELIABLE_IMAGES
from multicam_ego_motion.ros_plumbing.recent_outputs import RecentOutputs

# Timeouts only: the normal path is driven by messages. Every timer wake-up makes rclpy's
# executor rebuild its wait set over all of the worker's entities, so poll slowly.
POLL_PERIOD_S = 0.1

NODE_PARAMETERS = {
    'camera': ('front', 'name of the camera whose quarters this arbiter fuses', None, None),
    'quarters': (4, 'number of quarter nodes of this camera', 1, 4),
    'sync_timeout_s': (0.5, 'longest wait for all quarters of one frame', 0.0, 60.0),
    'debug_images': (False, 'publish tracks (/<cam>/tracks, bgr8): the quarters\' debug images (their debug_images) put together, the tracked features, their flow and landmark/epipolar status drawn; off: nothing subscribed or published', None, None),
}
FUSION_PARAMETERS = quarter_fusion.PARAMETERS


class CameraArbiterNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('camera_arbiter', **node_kwargs)
        p = declare_from_table(self, NODE_PARAMETERS)
        self.fusion_params = declare_from_table(self, FUSION_PARAMETERS)
        self.camera = p['camera']
        sources = [f'q{i}' for i in range(1, p['quarters'] + 1)]
        self.sync = StampSynchronizer(sources, p['sync_timeout_s'])
        self.pub = self.create_publisher(PoseWithCovarianceStamped, 'pose', RELIABLE)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE)
        self.diag_sink = None        # hook(stamp, status): the worker batches statuses per frame
        # hook(msg) instead of only publishing: a worker hands the camera's estimate to a
        # co-hosted general arbiter directly (which then does not subscribe to it)
        self.estimate_sink = None
        self.sources = sources
        self.sent = RecentOutputs()      # stamp -> published camera pose
        self.quarter_subs = {}
        self.debug_images = bool(p['debug_images'])
        self.tracks_subs = {}
        if self.debug_images:
            self.tracks_sync = StampSynchronizer(sources, p['sync_timeout_s'])
            self.tile_sizes = {}         # quarter -> (width, height) of its tiles seen so far
            self.pub_tracks = self.create_publisher(Image, 'tracks', RELIABLE_IMAGES)
        self.take_local(())
        self.poll_timer = self.create_timer(POLL_PERIOD_S, self.poll)

    def take_local(self, local):
        """Quarters (`q1`...) whose estimates a host hands to on_quarter itself (worker.py:
        co-hosted quarters): no subscription for them, every other one subscribed."""
        subscribe_remote(self, self.quarter_subs, self.sources, local, lambda s: self.create_subscription(
            PoseWithCovarianceStamped, f'{s}/pose', lambda m: self.on_quarter(s, m), RELIABLE))
        # debug_images: their tiles likewise
        subscribe_remote(self, self.tracks_subs, self.sources if self.debug_images else (), local,
                         lambda s: self.create_subscription(
                             Image, f'{s}/tracks', lambda m: self.on_tracks(s, m), RELIABLE_IMAGES))

    def on_quarter(self, source, msg):
        est = msg_to_estimate(msg, source=f'{self.camera}/{source}')
        sent = self.sent.get(est.stamp_ns)        # (only released frames are kept)
        if sent is not None:
            # A quarter sent a frame's estimate again (the frame was re-published after a
            # worker restart): this camera's pose of it again, for a restored general arbiter.
            self.send(sent)
        self.release(self.sync.add(source, est.stamp_ns, est, time.monotonic()))

    def poll(self):
        """Sync timeouts; called every POLL_PERIOD_S by the node's own timer, or by its
        worker's one timer for all its nodes (worker.py)."""
        now = time.monotonic()
        self.release(self.sync.poll(now))
        if self.debug_images:
            self.release_tracks(self.tracks_sync.poll(now))

    def release(self, groups):
        for g in groups:
            t0 = time.thread_time()
            # Quarter order, not arrival order: float sums must not depend on the scheduler.
            fused = fuse_quarters([g.items[k] for k in sorted(g.items)], source=self.camera,
                                  **self.fusion_params)
            msg = estimate_to_msg(fused)
            self.sent.add(g.stamp_ns, msg)
            ms = (time.thread_time() - t0) * 1e3
            level = 'warn' if g.missing or not fused.informative else 'ok'
            text = f'missing quarters: {", ".join(g.missing)}' if g.missing else fused.state
            # Status before the estimate (see quarter_node.process): the general arbiter's
            # snapshot must not precede this frame's batch of statuses.
            diagnostics.emit(ns_to_stamp(g.stamp_ns), diagnostics.status(
                f'ego_motion/{self.camera}/arbiter', level, text,
                {'quarters': len(g.items), 'state': fused.state, 'arbiter_ms': ms},
                hardware_id=self.camera), self.diag_sink, self.pub_diag)
            self.send(msg)

    def send(self, msg):
        # With the general arbiter co-hosted, published only for other listeners (a
        # recorder, a viewer): a publish without subscribers still costs.
        if self.estimate_sink is None or self.pub.get_subscription_count() > 0:
            self.pub.publish(msg)
        if self.estimate_sink is not None:
            self.estimate_sink(msg)

    # --- debug_images ----------------------------------------------------------------------
    def on_tracks(self, source, msg: Image):
        """A quarter's tile (bgr8) of one frame."""
        if msg.encoding != 'bgr8' or msg.step != 3 * msg.width \
                or len(msg.data) != msg.step * msg.height:
            self.get_logger().warning(f'{self.camera}: {source} tracks image ignored '
                                      f'({msg.encoding} {msg.width}x{msg.height}, step {msg.step})',
                                      throttle_duration_sec=5.0)
            return
        tile = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width, 3)
        q = int(source[1:])
        self.tile_sizes[q] = (msg.width, msg.height)
        self.release_tracks(self.tracks_sync.add(source, stamp_to_ns(msg.header.stamp),
                                                 (tile, msg.header.frame_id), time.monotonic()))

    def release_tracks(self, groups):
        from camera_pose_nodes.track_image import compose_quarters
        for g in groups:
            tiles = {int(s[1:]): tile for s, (tile, _) in g.items.items()}
            img = compose_quarters(tiles, self.tile_sizes)
            if img is None:
                continue
            self.pub_tracks.publish(bgr8_message(Image(), img, ns_to_stamp(g.stamp_ns),
                                                 next(iter(g.items.values()))[1]))


def main(args=None):
    return spin_node(CameraArbiterNode, 'camera_arbiter', args)
