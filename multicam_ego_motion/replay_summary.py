"""After a replay: odometry.tum, the evaluation against ground truth, and the summary table."""
from pathlib import Path

from multicam_ego_motion.errors import UserError


def summarize(bag, reader, out: Path, counts: dict, playback, wall_s: float, total_s: float,
              gt_topic: str) -> int:
    from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories, summary_rows
    from multicam_ego_motion.evaluation.trajectory_io import read_bag_topic, save_tum

    n_odom = counts.get('/odom', 0)
    if n_odom == 0:
        raise UserError(f'the graph published no /odom (see {out / "logs"})')
    est = read_bag_topic(out / 'output', '/odom')
    save_tum(est, out / 'odometry.tum')
    frames = playback.frames if playback else 0
    bag_s = (est.stamps[-1] - est.stamps[0]) if len(est) > 1 else 0.0
    rows = [('frames played', f'{frames}'), ('/odom messages', f'{n_odom}'),
            ('replay wall time [s]', f'{wall_s:.1f} (total with start-up {total_s:.1f})'),
            ('real-time factor', f'{bag_s / wall_s:.2f}' if wall_s > 0 else 'n/a')]
    if gt_topic in reader.topics:
        ref = read_bag_topic(bag, gt_topic)
        metrics = evaluate_trajectories(ref, est, out_dir=out)
        rows = summary_rows(metrics) + rows
    else:
        rows.append(('ground truth', f'none ({gt_topic} not in the bag)'))
    width = max(len(r[0]) for r in rows)
    print('\n'.join(f'{k:<{width}}  {v}' for k, v in rows))
    print(f'outputs: {out}/output (bag), {out}/odometry.tum'
          + (f', {out}/report.md, {out}/trajectory.png' if gt_topic in reader.topics else ''))
    return 0
