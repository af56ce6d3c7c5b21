"""Keep every run on its own DDS domain, on localhost only, unless the user chose otherwise:
a replay must never talk to a robot (or another test) on the same network."""
import os
import socket

# RTPS default port mapping: domain d uses the UDP ports 7400 + 250 d ... + 249 (discovery
# multicast, then two unicast ports per participant). 1..100 stays below the Linux
# ephemeral range (32768), so a bound port there belongs to a DDS participant.
PORT_BASE, DOMAIN_GAIN = 7400, 250
DOMAINS = range(1, 101)
# The last port of a domain's range (participant 119's user unicast port: never reached) is
# bound by the process that took the domain, for as long as it runs: a domain looks free
# only when it is, also between one run's start and its first participant.
RESERVE_OFFSET = DOMAIN_GAIN - 1
_reservations = {}          # domain -> the socket that holds it


def _udp_ports_in_use():
    ports = set()
    for table in ('/proc/net/udp', '/proc/net/udp6'):
        try:
            rows = open(table).read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            ports.add(int(row.split()[1].rsplit(':', 1)[1], 16))
    return ports


def _free_domains(seed: int):
    """The domains no participant on this host uses right now, in search order from a
    pid-spread start (two runs picking at the same instant rarely start from the same place)."""
    used = _udp_ports_in_use()
    start = seed % len(DOMAINS)
    for k in range(len(DOMAINS)):
        d = DOMAINS[(start + k) % len(DOMAINS)]
        lo = PORT_BASE + DOMAIN_GAIN * d
        if not any(lo <= p < lo + DOMAIN_GAIN for p in used):
            yield d


def _seed(seed):
    return os.getpid() * 7919 if seed is None else seed


def free_domain(seed: int = None) -> int:
    """A domain no participant on this host uses right now (_free_domains). Falls back to
    the start when every domain looks busy or /proc is not there."""
    seed = _seed(seed)
    return next(_free_domains(seed), DOMAINS[seed % len(DOMAINS)])


def reserve_domain(seed: int = None) -> int:
    """A free domain (free_domain), held by this process until it exits: two runs that
    start at the same instant, or one that picks while another has no participant yet
    (between its tests, or before its workers start), never share it. Falls back to an
    unheld free domain (the first one seen, else the start) when no port can be bound."""
    seed = _seed(seed)
    first = None
    for d in _free_domains(seed):
        first = d if first is None else first
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(('', PORT_BASE + DOMAIN_GAIN * d + RESERVE_OFFSET))
        except OSError:         # taken between the look and the bind: the next one
            sock.close()
            continue
        _reservations[d] = sock
        return d
    return first if first is not None else DOMAINS[seed % len(DOMAINS)]


def isolate(env=None) -> dict:
    env = os.environ if env is None else env
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if 'ROS_DOMAIN_ID' not in env:
        # pid-spread alone let two concurrent runs share a domain and see each other's frames;
        # a look at the ports alone, two that picked before either had a participant.
        env['ROS_DOMAIN_ID'] = str(reserve_domain())
    return env
