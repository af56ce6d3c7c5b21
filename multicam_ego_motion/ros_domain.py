"""Keep every run on its own DDS domain, on localhost only, unless the user chose otherwise:
a replay must never talk to a robot (or another test) on the same network."""
import os


def isolate(env=None) -> dict:
    env = os.environ if env is None else env
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if 'ROS_DOMAIN_ID' not in env:
        # 1..100: valid on Linux for the default port mapping; pid spreads parallel runs.
        env['ROS_DOMAIN_ID'] = str(1 + (os.getpid() * 7919) % 100)
    return env
