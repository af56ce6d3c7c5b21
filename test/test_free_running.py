"""Free-running cameras through the whole graph (real nodes over DDS, 2 workers): cameras that
capture 0, 16, 32 and 48 ms after the frame clock (a spread no sync window groups at 15 Hz),
cameras with random phases, and four rates at once (30, 20, 15 and 10 Hz). The general arbiter
fuses every estimate at its own stamp, in stamp order (estimates with identical stamps
together), and feeds the fused pose back at that stamp; the lockstep player plays every image
as a frame of its own, with one more frame in flight than the rig has cameras.

The loop: 10 s, 320 x 240, fx 200, seed 7 (2.5 m/s at its fastest). Lockstep accuracy is
asserted against absolute limits (the accuracy suite's loop limits, 0.6 % ATE and 0.7 % final
drift at 8 Hz, with the margin a faster, shorter run needs) and, for the fixed offsets and the
mixed rates, against the synchronised run of the same scene. Random phases meet the absolute
limits and, on this seed, come within 20 % of the synchronised run (over seeds 7-11 not every
seed does: docs/fusion.md gives the figures), each camera's rotation between its frames
measured on its tracks (lone_camera_track_rotation). Rate-mode
accuracy depends on the machine's load: here rate mode must run through and fuse what it
takes without timeouts.
"""
import numpy as np
import pytest

from replay_run import replay
from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
from multicam_ego_motion.evaluation.trajectory_io import load_trajectory
from multicam_ego_motion.scenarios.generator import generate, random_phases_ms

LOOP = dict(seed=7, duration=10.0, width=320, height=240, fx=200.0, progress=False)
OFFSETS_MS = [0, 16, 32, 48]
MIXED_RATES = [30, 20, 15, 10]
ATE_LIMIT_PCT, DRIFT_LIMIT_PCT = 0.8, 0.9
RELATIVE = 1.2               # within 20 % of the synchronised run
START_S = 0.25               # every camera's second image is in by then (10 Hz: 0.1-0.2 s)
CAMERAS = ['/back/image_raw', '/front/image_raw', '/left/image_raw', '/right/image_raw']


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('free_running')
    b = {k: root / k for k in ('sync', 'offsets', 'random', 'mixed')}
    generate('loop', b['sync'], rate=15.0, **LOOP)
    generate('loop', b['offsets'], rate=15.0, camera_offsets_ms=OFFSETS_MS, **LOOP)
    generate('loop', b['random'], rate=15.0, camera_phases='random', **LOOP)
    generate('loop', b['mixed'], rate=30.0, camera_rates=MIXED_RATES, **LOOP)
    return b


def scored(run):
    assert run.returncode == 0, run
    ref = load_trajectory(f'{run.bag}:/ground_truth/odom')
    est = load_trajectory(str(run.output), topic='/odom')
    return evaluate_trajectories(ref, est)


def camera_stamps(bag):
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.ros_plumbing.pose_messages import stamp_to_ns
    r = Rosbag2Reader(bag)
    topics = [t for t in r.topics if t.endswith('/image_raw')]
    return {t: [stamp_to_ns(m.header.stamp) for _, m, _ in r.decoded([t])] for t in topics}


def timed_out(run):
    return [d for d in run.diagnostics('ego_motion/general_arbiter')
            if d.values.get('sync_timed_out') == 'True']


@pytest.fixture(scope='module')
def runs(bags, tmp_path_factory):
    root = tmp_path_factory.mktemp('free_running_runs')
    # The start allocation for the fusion's tests: without moves the graph equals the sequential
    # pipeline to 1e-15; a moved node computes on in another process, whose float rounding
    # this estimator grows to millimetres (moves are tested on their own below).
    out = {k: replay(bags[k], root / k, '--no-rebalance') for k in ('sync', 'offsets', 'random', 'mixed')}
    # and with nodes moving: a quarter every 40 frames, and whatever the costs ask for. (A
    # moved node's first frame on a loaded machine took longer than the player's 2 s
    # stall-ahead, which then let frames out past it: they were fused together. That is
    # not what this run is about; 10 s still brings a sample lost at discovery.)
    out['random_moves'] = replay(bags['random'], root / 'random_moves', '--migrate-every', 40,
                                 '--stall-ahead', 10)
    return out


def test_random_phases_are_seeded_and_within_the_period(bags):
    phases = random_phases_ms(7, [15.0] * 4)
    assert phases == random_phases_ms(7, [15.0] * 4) != random_phases_ms(8, [15.0] * 4)
    assert all(0 <= p < 1000 / 15 for p in phases) and len(set(phases)) == 4
    assert all(0 <= p < 1000 / r for p, r in zip(random_phases_ms(3, MIXED_RATES), MIXED_RATES))
    stamps = camera_stamps(bags['random'])
    first = min(s[0] for s in stamps.values())
    got = sorted((s[0] - first) / 1e6 for s in stamps.values())
    want = sorted(p - min(phases) for p in phases)
    assert np.allclose(got, want, atol=1e-3), (got, want)
    assert all(len(s) == 151 for s in stamps.values())


def test_generator_refuses_bad_camera_timing(tmp_path):
    from multicam_ego_motion.errors import UserError
    with pytest.raises(UserError, match='has 3 value.*4 cameras'):
        generate('loop', tmp_path / 'a', rate=15.0, camera_offsets_ms=[0, 8, 16], **LOOP)
    with pytest.raises(UserError, match='camera 3 offset.*frame period'):
        generate('loop', tmp_path / 'b', rate=15.0, camera_offsets_ms=[0, 8, 16, 70], **LOOP)
    with pytest.raises(UserError, match='camera 1 rate'):
        generate('loop', tmp_path / 'c', rate=15.0, camera_rates=[15, 500, 15, 15], **LOOP)
    with pytest.raises(UserError, match='exclude each other'):
        generate('loop', tmp_path / 'd', rate=15.0, camera_offsets_ms=[0, 8, 16, 24],
                 camera_phases='random', **LOOP)


def test_ground_truth_at_every_capture_instant(bags):
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.ros_plumbing.pose_messages import stamp_to_ns
    gt = {stamp_to_ns(m.header.stamp) for _, m, _ in
          Rosbag2Reader(bags['random']).decoded(['/ground_truth/odom'])}
    for topic, stamps in camera_stamps(bags['random']).items():
        assert set(stamps) <= gt, topic


def every_image_fused_alone(run, bag, stalls=True):
    """One /odom per distinct camera stamp, each fused from the cameras of that stamp, none
    after a timeout and (stalls) no lockstep frame let out past a stalled one."""
    stamps = sorted({s for v in camera_stamps(bag).values() for s in v})
    odom, _, _, _ = run.odometry()
    assert [round(s, 6) for s in odom] == [round((s - run.start_ns) / 1e9, 6) for s in stamps]
    # (the bag's last image may wait for a camera that is due just after it, and whose image
    # the bag ends before: one timeout there, none before)
    assert not [d for d in timed_out(run) if d.t < odom[-1] - 0.07]
    assert not stalls or 'stalled' not in run.stdout, run.stdout[-2000:]
    diags = run.diagnostics('ego_motion/general_arbiter')
    assert len(diags) == len(stamps)
    # no camera named missing once every camera's period is known (from its second image),
    # up to the end's wait for an image the bag does not have
    named = [(d.t, d.values['cameras_missing']) for d in diags
             if d.values['cameras_missing'] and START_S < d.t < odom[-1] - 0.07]
    assert not named, named
    used = sum(len(d.values['cameras_used'].split(',')) for d in diags if d.values['cameras_used'])
    return used


def test_offsets_over_most_of_the_period_lockstep(runs, bags):
    run = runs['offsets']
    assert 'cameras capture up to 32.0 ms apart (shortest frame period 66.7 ms): free-running, ' \
        'each camera fused at its own stamp' in run.stdout, run.stdout
    assert 'free-running' not in runs['sync'].stdout
    # nearly every image is used (each camera's first starts its map; 2 % are gated out)
    assert every_image_fused_alone(run, bags['offsets']) >= 0.97 * 4 * 150
    sync, off = scored(runs['sync']), scored(run)
    assert off['ate_pct'] <= RELATIVE * sync['ate_pct'], (off['ate_pct'], sync['ate_pct'])
    assert off['final_drift_pct'] <= RELATIVE * sync['final_drift_pct'], \
        (off['final_drift_pct'], sync['final_drift_pct'])
    assert off['ate_pct'] <= ATE_LIMIT_PCT and off['final_drift_pct'] <= DRIFT_LIMIT_PCT


def test_random_phases_lockstep(runs, bags):
    assert every_image_fused_alone(runs['random'], bags['random']) >= 0.97 * 4 * 150
    m, sync = scored(runs['random']), scored(runs['sync'])
    assert m['ate_pct'] <= ATE_LIMIT_PCT and m['final_drift_pct'] <= DRIFT_LIMIT_PCT, m
    # (seed 7: 0.26 / 0.07 % against 0.34 / 0.28 synchronised; without the cameras' own
    # rotations 0.19 / 0.29)
    assert m['ate_pct'] <= RELATIVE * sync['ate_pct'], (m, sync)
    assert m['final_drift_pct'] <= RELATIVE * sync['final_drift_pct'], (m, sync)
    # every camera alone at its stamp, its rotation from the frame before measured on its tracks
    diags = runs['random'].diagnostics('ego_motion/general_arbiter')
    assert int(diags[-1].values['lone_track_rotations']) >= 0.8 * 4 * 150
    assert int(runs['sync'].diagnostics('ego_motion/general_arbiter')[-1].values['lone_track_rotations']) == 0


def test_lockstep_equals_the_sequential_pipeline_with_random_phases(runs, bags):
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import fusion_params_from, quarter_params_from
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.ros_plumbing.package_share import default_params
    from multicam_ego_motion.sequential_pipeline import run_sequential
    params = default_params()
    rig, _ = resolve_rig(Rosbag2Reader(bags['random']), None)
    res = run_sequential(bags['random'], rig, quarter_params_from(params), fusion_params_from(params))
    _, poses, _, _ = runs['random'].odometry()
    assert len(res.fused) == len(poses) == 604
    # The same to float rounding (7e-16 measured: a pose's quaternion round trip). The 0.2 and
    # 1.7 mm that 2 of 3 CI runs once read came from rebalancing moves: a moved node's frame was
    # fused without its wheel reading after wheel_wait_s (see the runs fixture).
    assert max(np.abs(f.T_odom_base - T).max() for f, T in zip(res.fused, poses)) < 1e-9


def test_four_rates_at_once_lockstep(runs, bags):
    # Until a camera's second image its period is unknown and every group waits for it: the
    # replay keeps enough frames in flight for that image to be out (no 2 s stall; there was
    # one at the start). Images not used: the first frame's (initializing) and the 10 Hz
    # camera's where the fusion leaves it out (its tracking in the turns)
    assert 'cameras at different rates or phases: 4 frames in flight' in runs['mixed'].stdout
    used = every_image_fused_alone(runs['mixed'], bags['mixed'])
    images = sum(len(v) for v in camera_stamps(bags['mixed']).values())
    assert used >= 0.94 * images
    sync, mixed = scored(runs['sync']), scored(runs['mixed'])
    assert mixed['ate_pct'] <= RELATIVE * sync['ate_pct'] and mixed['ate_pct'] <= ATE_LIMIT_PCT
    assert mixed['final_drift_pct'] <= RELATIVE * sync['final_drift_pct']
    assert mixed['final_drift_pct'] <= DRIFT_LIMIT_PCT


def test_rate_mode_with_random_phases_fuses_what_it_takes(bags, tmp_path):
    # Real time: the graph skips what it cannot keep up with (the frame schedule), but fuses
    # each estimate it gets at its own stamp, without waiting for a sync timeout.
    run = replay(bags['random'], tmp_path / 'rate', '--rate', '1', '--duration', '4')
    assert run.returncode == 0, run
    stamps, _, _, _ = run.odometry()
    assert len(stamps) >= 40                          # of 240 images played
    diags = run.diagnostics('ego_motion/general_arbiter')
    assert len(timed_out(run)) <= len(diags) // 10, [d.t for d in timed_out(run)]


def test_lockstep_player_plays_each_image_as_a_frame(bags):
    from multicam_ego_motion.bag.player import BagPlayer, PlayOptions
    frames = [f for f in BagPlayer(bags['random'], PlayOptions(lockstep=True)).frames() if f.is_trigger]
    assert len(frames) == 604
    assert [f.stamp_ns for f in frames] == sorted(s for v in camera_stamps(bags['random']).values() for s in v)
    # an explicit window still groups a frame's images (sync_window_s, opt-in)
    grouped = [f for f in BagPlayer(bags['offsets'], PlayOptions(lockstep=True, sync_window_s=0.03)).frames()
               if f.is_trigger]
    assert all(sum(m.topic in CAMERAS for m in f.messages) <= 2 for f in grouped) and len(grouped) == 302


def test_nodes_move_between_frames_with_random_phases(runs, bags):
    """Moves in a free-running lockstep replay: a node whose frame waits for an image or a
    wheel reading the player holds back during the move stays, and its move is tried again
    between later frames, so every node moves between its frames. (Before, such a move waited
    2 s, then took the node mid-frame: mm off the pipeline, and once a sync timeout.) The
    odometry is the unmoved run's up to float rounding, which this chaotic estimator grows:
    1e-12 at the first difference (frame 318 of 604), 3 mm at the end, measured."""
    run = runs['random_moves']
    moves = [l for l in run.stdout.splitlines() if l.startswith('coordinator: moved ')]
    assert len(moves) >= 8, run.stdout[-3000:]
    assert not [l for l in moves if 'mid-frame' in l], moves
    every_image_fused_alone(run, bags['random'])
    _, moved, _, _ = run.odometry()
    _, still, _, _ = runs['random'].odometry()
    assert len(moved) == len(still) == 604
    assert max(np.abs(a - b).max() for a, b in zip(moved, still)) < 0.02
