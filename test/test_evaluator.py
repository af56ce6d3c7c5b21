"""The evaluator: agreement with evo, known answers, TUM round trip, report files."""
import copy

import numpy as np
import pytest
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from multicam_ego_motion import cli
from multicam_ego_motion.evaluation.association import associate
from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
from multicam_ego_motion.evaluation.metrics import compute_metrics, rpe_segments, travelled_distances
from multicam_ego_motion.evaluation.trajectory_io import (Trajectory, load_trajectory,
                                                          load_tum, save_tum)

TOL = 1e-6


def curvy_reference(n=600, dt=0.05):
    """A 3D figure-eight-ish drive with changing heading, pitch and height (about 40 m)."""
    t = np.arange(n) * dt
    pos = np.column_stack([8 * np.sin(0.2 * t), 5 * np.sin(0.4 * t), 0.5 * np.sin(0.3 * t)])
    vel = np.gradient(pos, axis=0)
    yaw = np.arctan2(vel[:, 1], vel[:, 0])
    pitch = -np.arctan2(vel[:, 2], np.linalg.norm(vel[:, :2], axis=1))
    rot = Rotation.from_euler('zyx', np.column_stack([yaw, pitch, 0.05 * np.sin(t)]))
    return Trajectory(1000.0 + t, pos, rot.as_quat())


def drifting_estimate(ref, scale=1.03, yaw_rate=0.004, noise=0.01, seed=3):
    """Scaled, slowly yawing away, noisy; stamps jittered by < 4 ms, every third pose dropped."""
    rng = np.random.default_rng(seed)
    poses = ref.poses()
    drift = Rotation.from_euler('z', yaw_rate * np.arange(len(ref))[:, None]).as_matrix()
    est = poses.copy()
    est[:, :3, 3] = scale * np.einsum('nij,nj->ni', drift, poses[:, :3, 3]) \
        + rng.normal(0, noise, (len(ref), 3))
    est[:, :3, :3] = drift @ poses[:, :3, :3] @ Rotation.from_rotvec(
        rng.normal(0, 0.002, (len(ref), 3))).as_matrix()
    keep = np.arange(len(ref)) % 3 != 2
    stamps = ref.stamps + rng.uniform(-0.004, 0.004, len(ref))
    return Trajectory.from_poses(stamps[keep], est[keep])


def evo_trajectory(traj):
    return PoseTrajectory3D(positions_xyz=traj.positions,
                            orientations_quat_wxyz=np.roll(traj.quats_xyzw, 1, axis=1),
                            timestamps=traj.stamps)


def evo_ape_rmse(ref, est):
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return ape.get_statistic(evo_metrics.StatisticsType.rmse)


def evo_rpe_errors(ref, est, relation, d):
    rpe = evo_metrics.RPE(relation, delta=d, delta_unit=evo_metrics.Unit.meters,
                          rel_delta_tol=0.1, all_pairs=True, pairs_from_reference=True)
    rpe.process_data((ref, est))
    return rpe.error, rpe.delta_ids


def test_metrics_equal_evo():
    ref = curvy_reference()
    est = drifting_estimate(ref)
    mine = evaluate_trajectories(ref, est, max_time_diff=0.01, rpe_distances=(1, 2, 5, 10))

    evo_ref, evo_est = evo_sync.associate_trajectories(
        evo_trajectory(ref), evo_trajectory(est), max_diff=0.01)
    assert mine['poses'] == evo_ref.num_poses == 400
    a_ref, a_est = associate(ref, est, 0.01)
    np.testing.assert_allclose(a_ref.stamps, evo_ref.timestamps, atol=0)
    np.testing.assert_allclose(a_est.stamps, evo_est.timestamps, atol=0)

    origin = copy.deepcopy(evo_est)
    origin.align_origin(evo_ref)
    assert mine['ate_rmse_m'] == pytest.approx(evo_ape_rmse(evo_ref, origin), abs=TOL)
    se3 = copy.deepcopy(evo_est)
    se3.align(evo_ref, correct_scale=False)
    assert mine['ate_se3_rmse_m'] == pytest.approx(evo_ape_rmse(evo_ref, se3), abs=TOL)
    sim3 = copy.deepcopy(evo_est)
    _, _, s = sim3.align(evo_ref, correct_scale=True)
    assert mine['ate_sim3_rmse_m'] == pytest.approx(evo_ape_rmse(evo_ref, sim3), abs=TOL)
    assert mine['sim3_scale'] == pytest.approx(s, abs=TOL)
    assert mine['scale_error_pct'] > 1.0  # built 3 % too long (the yaw drift distorts more)
    assert mine['ate_rmse_m'] > mine['ate_se3_rmse_m'] > mine['ate_sim3_rmse_m'] > 0.005

    distances = travelled_distances(a_ref.positions)
    for d in (1, 2, 5, 10):
        trans, ends = evo_rpe_errors(evo_ref, evo_est, evo_metrics.PoseRelation.translation_part, d)
        rot, _ = evo_rpe_errors(evo_ref, evo_est, evo_metrics.PoseRelation.rotation_angle_deg, d)
        pairs, my_trans, my_rot, seg = rpe_segments(a_ref.poses(), a_est.poses(), distances, d)
        assert [j for _, j in pairs] == list(ends) and len(pairs) > 10
        np.testing.assert_allclose(my_trans, trans, atol=TOL)
        np.testing.assert_allclose(my_rot, rot, atol=TOL)
        assert np.all(np.abs(seg - d) <= 0.1 * d)
        assert mine[f'rpe_{d}m_pairs'] == len(pairs)
        assert mine[f'rpe_{d}m_trans_pct'] == pytest.approx(100 * np.mean(trans / seg), abs=TOL)
        assert mine[f'rpe_{d}m_rot_deg_per_m'] == pytest.approx(np.mean(rot / seg), abs=TOL)

    length = float(np.sum(np.linalg.norm(np.diff(evo_ref.positions_xyz, axis=0), axis=1)))
    assert mine['path_length_m'] == pytest.approx(length, abs=TOL)
    final = np.linalg.norm(origin.positions_xyz[-1] - evo_ref.positions_xyz[-1])
    assert mine['final_drift_pct'] == pytest.approx(100 * final / length, abs=TOL)
    rel = evo_ref.poses_se3[-1][:3, :3].T @ origin.poses_se3[-1][:3, :3]
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec()))
    assert mine['rotation_drift_deg_per_m'] == pytest.approx(angle / length, abs=TOL)


def straight_line(n=401, step=0.05):
    """x from 0 to 20 m, facing +x: pairs of any whole-metre distance exist exactly."""
    pos = np.column_stack([np.arange(n) * step, np.zeros(n), np.zeros(n)])
    return Trajectory(np.arange(n) * 0.1, pos, np.tile([0, 0, 0, 1.0], (n, 1)))


def test_scale_known_answer():
    ref = straight_line()
    est = Trajectory(ref.stamps, 1.02 * ref.positions, ref.quats_xyzw)
    m = compute_metrics(ref.poses(), est.poses(), rpe_distances=(1, 2, 5, 50))
    assert m['scale_error_pct'] == pytest.approx(2.0, abs=1e-9)
    assert m['ate_sim3_rmse_m'] == pytest.approx(0.0, abs=1e-9)
    assert m['final_drift_pct'] == pytest.approx(2.0, abs=1e-9)
    for d in (1, 2, 5):
        assert m[f'rpe_{d}m_trans_pct'] == pytest.approx(2.0, abs=1e-9)
        assert m[f'rpe_{d}m_rot_deg_per_m'] == pytest.approx(0.0, abs=1e-9)
    assert 'rpe_50m_trans_pct' not in m  # longer than the 20 m path
    assert m['rotation_drift_deg_per_m'] == pytest.approx(0.0, abs=1e-9)


def test_offset_known_answers():
    ref = straight_line()
    c = np.array([0.0, 0.3, 0.4])  # |c| = 0.5 m
    shifted = Trajectory(ref.stamps, ref.positions + c, ref.quats_xyzw)
    m = compute_metrics(ref.poses(), shifted.poses())
    assert m['ate_rmse_m'] == pytest.approx(0.0, abs=1e-9)  # first-pose alignment removes it
    assert m['ate_se3_rmse_m'] == pytest.approx(0.0, abs=1e-9)
    # alternating +c/-c: after first-pose alignment half the poses are 2|c| off
    sign = np.where(np.arange(len(ref)) % 2 == 0, 1.0, -1.0)[:, None]
    zigzag = Trajectory(ref.stamps, ref.positions + sign * c, ref.quats_xyzw)
    n = len(ref)
    expected = np.sqrt((n // 2) * (2 * 0.5) ** 2 / n)
    assert compute_metrics(ref.poses(), zigzag.poses())['ate_rmse_m'] == pytest.approx(expected, abs=1e-9)


def test_rotation_drift_known_answer():
    ref = straight_line()
    # the estimate ends turned by 4 degrees about z at the end of the 20 m path
    yaw = np.radians(4.0) * np.arange(len(ref)) / (len(ref) - 1)
    est = Trajectory(ref.stamps, ref.positions, Rotation.from_euler('z', yaw[:, None]).as_quat())
    m = compute_metrics(ref.poses(), est.poses())
    assert m['rotation_drift_deg_per_m'] == pytest.approx(4.0 / 20.0, abs=1e-9)


def test_tum_round_trip(tmp_path):
    ref = curvy_reference(n=50)
    save_tum(ref, tmp_path / 'ref.tum')
    back = load_tum(tmp_path / 'ref.tum')
    np.testing.assert_allclose(back.stamps, ref.stamps, atol=1e-9)
    np.testing.assert_allclose(back.positions, ref.positions, atol=1e-9)
    np.testing.assert_allclose(back.quats_xyzw, ref.quats_xyzw, atol=1e-8)


def test_report_and_plots(tmp_path):
    from matplotlib.image import imread
    ref = curvy_reference(n=300)
    metrics = evaluate_trajectories(ref, drifting_estimate(ref), out_dir=tmp_path)
    assert metrics['poses'] == 200
    for name in ('trajectory.png', 'error_over_distance.png'):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b'\x89PNG\r\n\x1a\n' and len(data) > 10_000
        assert imread(tmp_path / name)[..., :3].std() > 0.05  # not a blank canvas
    report = (tmp_path / 'report.md').read_text()
    assert '![trajectory](trajectory.png)' in report
    assert '![error over distance](error_over_distance.png)' in report
    assert f"| ATE RMSE, aligned on first pose [m] | {metrics['ate_rmse_m']:.4f} |" in report
    assert len(load_tum(tmp_path / 'estimate.tum')) == 200


def _write_pose_bag(path, ref, est):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry, Path
    from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer

    def fill(header, pose, traj, i):
        header.stamp.sec, header.stamp.nanosec = divmod(int(round(traj.stamps[i] * 1e9)), 10**9)
        pose.position.x, pose.position.y, pose.position.z = traj.positions[i]
        q = traj.quats_xyzw[i]
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q

    path_msg = Path()
    with Rosbag2Writer(path) as w:
        for i in range(len(ref)):
            odom = Odometry()
            fill(odom.header, odom.pose.pose, ref, i)
            w.write('/ground_truth', odom, int(ref.stamps[i] * 1e9))
        for i in range(len(est)):
            ps = PoseStamped()
            fill(ps.header, ps.pose, est, i)
            w.write('/estimate', ps, int(est.stamps[i] * 1e9))
            path_msg.poses.append(ps)
            w.write('/path', path_msg, int(est.stamps[i] * 1e9))


def test_cli_on_bag_topics(tmp_path, capsys):
    ref = curvy_reference(n=120)
    est = drifting_estimate(ref)
    _write_pose_bag(tmp_path / 'run', ref, est)
    from_path = load_trajectory(tmp_path / 'run', topic='/path')  # last Path message
    np.testing.assert_allclose(from_path.positions, est.positions, atol=1e-12)

    rc = cli.main(['evaluate', '--reference', f'{tmp_path / "run"}:/ground_truth',
                   '--estimate', str(tmp_path / 'run'), '--estimate-topic', '/estimate',
                   '--out', str(tmp_path / 'eval')])
    assert rc == 0
    expected = evaluate_trajectories(ref, est)
    out = capsys.readouterr().out
    assert f"{expected['ate_rmse_m']:.4f}" in out and 'ATE RMSE' in out
    assert (tmp_path / 'eval' / 'report.md').exists()

    rc = cli.main(['evaluate', '--reference', f'{tmp_path / "run"}:/nope',
                   '--estimate', f'{tmp_path / "run"}:/estimate', '--out', str(tmp_path / 'x')])
    err = capsys.readouterr().err
    assert rc == 2 and 'has no topic /nope' in err and len(err.strip().splitlines()) == 1


def test_umeyama_equals_evo_and_accepts_a_straight_line():
    from evo.core.geometry import umeyama_alignment
    from multicam_ego_motion.evaluation.alignment import umeyama
    ref = curvy_reference(n=200)
    est = drifting_estimate(ref)
    a_ref, a_est = associate(ref, est)
    for with_scale in (False, True):
        R, t, s = umeyama(a_est.positions, a_ref.positions, with_scale)
        R_evo, t_evo, s_evo = umeyama_alignment(a_est.positions.T, a_ref.positions.T, with_scale)
        np.testing.assert_allclose(R, R_evo, atol=1e-9)
        np.testing.assert_allclose(t, t_evo, atol=1e-9)
        assert s == pytest.approx(s_evo, abs=1e-12)
    line = straight_line().positions
    R, t, s = umeyama(line, 2.0 * line + [1, 2, 3], with_scale=True)
    np.testing.assert_allclose(s * line @ R.T + t, 2.0 * line + [1, 2, 3], atol=1e-9)
