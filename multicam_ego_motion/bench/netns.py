"""Hosts on one machine: Linux network namespaces linked by veth pairs to a bridge, with
their own addresses (10.77.0.1, .2, ...) and nothing outside. The multi-host test and the
bench's two-host row run the coordinator in one and remote workers in the others: every
byte between them crosses a network stack as between machines.

DDS across them: a Fast DDS profile per host with UDPv4 only (shared memory would still work
between namespaces of one kernel, which real hosts cannot do), bound to the host's address,
and the other hosts as initial peers (no reliance on multicast across the bridge).
Needs root and `ip` (iproute2); `unavailable()` says why not.
"""
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

SUBNET = '10.77.0'
PROFILE = '''<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>host_udp</transport_id>
      <type>UDPv4</type>
      <interfaceWhiteList><address>{address}</address></interfaceWhiteList>
      <maxInitialPeersRange>32</maxInitialPeersRange>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="ego_motion_host" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>host_udp</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <initialPeersList>
{peers}
        </initialPeersList>
      </builtin>
    </rtps>
  </participant>
</profiles>
'''
PEER = '          <locator><udpv4><address>{}</address></udpv4></locator>'


def _ip(*args, check=True):
    return subprocess.run(['ip', *args], capture_output=True, text=True, check=check)


def unavailable():
    """None when namespaces can be made here, else the reason (for a skip)."""
    if shutil.which('ip') is None:
        return 'no `ip` command (iproute2) to make network namespaces'
    if os.geteuid() != 0:
        return 'network namespaces need root (this runs as uid %d)' % os.geteuid()
    probe = f'egm_probe_{os.getpid()}'
    r = _ip('netns', 'add', probe, check=False)
    if r.returncode:
        return f'cannot create a network namespace: {r.stderr.strip()}'
    _ip('netns', 'del', probe, check=False)
    return None


class Hosts:
    """`n` namespaces named egm<pid>_h<i> with addresses SUBNET.<i+1>, a hub namespace with
    the bridge. A context manager: everything (processes started by run(), namespaces) goes
    at exit, also on failure."""

    def __init__(self, n: int, domain_id: int):
        self.n = n
        self.tag = f'egm{os.getpid()}'
        self.names = [f'{self.tag}_h{i}' for i in range(n)]
        self.hub = f'{self.tag}_hub'
        self.addresses = [f'{SUBNET}.{i + 1}' for i in range(n)]
        self.domain_id = domain_id
        self.folder = Path(tempfile.mkdtemp(prefix='ego_motion_hosts_'))
        self.procs = []

    def __enter__(self):
        try:
            self._make()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()

    def _make(self):
        _ip('netns', 'add', self.hub)
        _ip('-n', self.hub, 'link', 'add', 'br0', 'type', 'bridge')
        _ip('-n', self.hub, 'link', 'set', 'br0', 'up')
        _ip('-n', self.hub, 'link', 'set', 'lo', 'up')
        for i, (name, address) in enumerate(zip(self.names, self.addresses)):
            _ip('netns', 'add', name)
            # created inside the hub: nothing of it ever appears in the machine's namespace
            _ip('-n', self.hub, 'link', 'add', f'p{i}', 'type', 'veth', 'peer', 'name', 'eth0',
                'netns', name)
            _ip('-n', self.hub, 'link', 'set', f'p{i}', 'master', 'br0')
            _ip('-n', self.hub, 'link', 'set', f'p{i}', 'up')
            _ip('-n', name, 'addr', 'add', f'{address}/24', 'dev', 'eth0')
            _ip('-n', name, 'link', 'set', 'eth0', 'up')
            _ip('-n', name, 'link', 'set', 'lo', 'up')
            peers = '\n'.join(PEER.format(a) for a in self.addresses)
            (self.folder / f'fastdds_{i}.xml').write_text(PROFILE.format(address=address, peers=peers))
        # the bridge forwards once its ports leave the listening state
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            r = subprocess.run(['ip', 'netns', 'exec', self.names[0], 'ping', '-c1', '-W1',
                                self.addresses[-1]], capture_output=True) if shutil.which('ping') else None
            if r is None or r.returncode == 0:
                break
            time.sleep(0.2)

    def env(self, i: int, base=None) -> dict:
        env = dict(os.environ if base is None else base)
        env.update(FASTRTPS_DEFAULT_PROFILES_FILE=str(self.folder / f'fastdds_{i}.xml'),
                   ROS_DOMAIN_ID=str(self.domain_id),
                   # the profile says where to discover; the rmw must not narrow it to localhost
                   ROS_AUTOMATIC_DISCOVERY_RANGE='SYSTEM_DEFAULT')
        env.pop('ROS_STATIC_PEERS', None)
        return env

    def run(self, i: int, cmd, env=None, **kw) -> subprocess.Popen:
        """Start `cmd` in host i (its environment: env(i, env))."""
        p = subprocess.Popen(['ip', 'netns', 'exec', self.names[i], *map(str, cmd)],
                             env=self.env(i, env), **kw)
        self.procs.append(p)
        return p

    def pids(self, i: int):
        r = _ip('netns', 'pids', self.names[i], check=False)
        return [int(p) for p in r.stdout.split()]

    def kill_host(self, i: int):
        """SIGKILL every process in host i (a host that crashed)."""
        pids = self.pids(i)
        for pid in pids:
            try:
                os.kill(pid, 9)
            except ProcessLookupError:
                pass
        return pids

    def close(self):
        for i in range(self.n):
            self.kill_host(i)
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                pass
        for name in self.names + [self.hub]:
            _ip('netns', 'del', name, check=False)
        shutil.rmtree(self.folder, ignore_errors=True)
