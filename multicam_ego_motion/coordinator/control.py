"""The control channel between the coordinator and its workers (ROS-free).

One listener per coordinator: a Unix-domain socket for the workers it starts itself, and a
TCP port for workers on other hosts when asked (`listen_tcp`). Not ROS: the coordinator must
reach a worker whose ROS side is stuck or still starting, and a node's state (numpy arrays,
tracks, landmarks) travels as one pickle, not as a message type. Images and estimates never
go here: they are DDS topics.

Authentication (both directions, a shared key that never travels):
  coordinator -> worker   MAGIC, server nonce (32 bytes)
  worker -> coordinator   client nonce, HMAC(key, 'worker' | server nonce | client nonce)
  coordinator -> worker   ACCEPTED + HMAC(key, 'coordinator' | client nonce | server nonce),
                          or REFUSED (the worker does not know the key) and the close
Then every frame is `length (4) | tag (32) | pickle`, tag = HMAC(session key, direction |
sequence number | pickle), the session key derived from the key and both nonces: a frame
that was forged, altered, replayed or reordered ends the connection before it is unpickled.
The channel is authenticated, not encrypted (node states are not secrets; a VPN or WireGuard
between hosts adds confidentiality).

Messages (tuples):
  worker -> coordinator  (HELLO, index, pid, host)      index -1: a hot spare; REMOTE: a
                                                        worker that joins from elsewhere
                         (SNAPSHOT, key, state_pickle)  a remote worker's node finished a frame
                                                        (local workers write snapshot_store.py)
                         (REPLY, request_id, dict)      answer to ATTACH / DETACH / LINKS
                         (COSTS, [((sec, nanosec), [(name, {key: value})])])
                                                        the hosted nodes' stage times of a few
                                                        frames (their /diagnostics values the
                                                        allocation reads)
                         (PING,)                        heartbeat
  coordinator -> worker  (WELCOME, index, config)       to a joining worker: its slot, the
                                                        graph's params (text), namespace and
                                                        remappings
                         (ATTACH, request_id, node_spec, state_pickle_or_None, wait_links)
                         (DETACH, request_id, key)      reply carries 'state' (a pickle)
                         (LINKS, request_id)            reply when the hosted nodes' links
                                                        inside the graph are matched
                         (PING,)                        heartbeat
                         (STOP,)
"""
import hashlib
import hmac
import os
import pickle
import secrets
import socket
import stat
import struct
import threading

from multicam_ego_motion.errors import UserError

HELLO, SNAPSHOT, REPLY, PING, WELCOME = 'hello', 'snapshot', 'reply', 'ping', 'welcome'
COSTS = 'costs'
ATTACH, DETACH, LINKS, STOP = 'attach', 'detach', 'links', 'stop'
REMOTE = -2                       # HELLO index of a worker that joins over TCP
KEY_ENV = 'EGO_MOTION_CONTROL_KEY'
MIN_KEY_CHARS = 16
MAGIC = b'EGOMOTION-CTRL/1'
NONCE = 32
TAG = 32
ACCEPTED, REFUSED = b'A', b'R'
HANDSHAKE_TIMEOUT_S = 10.0
MAX_FRAME = 1 << 30
HEARTBEAT_S = 1.0                 # a PING each way this often on TCP connections
HEARTBEAT_TIMEOUT_S = 5.0         # nothing heard for this long: the peer (or its host) is gone


class AuthError(ConnectionError):
    """The other side does not know the key (or is not a control channel at all)."""


# ---- keys -------------------------------------------------------------------------------------
def load_key(key_file=None, env=None) -> bytes:
    """The shared key: the file's content (stripped) or $EGO_MOTION_CONTROL_KEY; never an
    argument (a command line is visible to every user of the host in ps)."""
    env = os.environ if env is None else env
    if key_file:
        try:
            mode = os.stat(key_file).st_mode
            text = open(key_file, 'rb').read().strip()
        except OSError as e:
            raise UserError(f'control key file {key_file}: {e.strerror}') from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            print(f'warning: control key file {key_file} is readable by other users (chmod 600 it)',
                  flush=True)
        source = f'key file {key_file}'
    elif env.get(KEY_ENV):
        text, source = env[KEY_ENV].strip().encode(), f'${KEY_ENV}'
    else:
        raise UserError(f'no control key: give --key-file FILE or set ${KEY_ENV} '
                        '(the same key on the coordinator and every worker)')
    if len(text) < MIN_KEY_CHARS:
        raise UserError(f'control key from {source} is too short ({len(text)} characters; '
                        f'at least {MIN_KEY_CHARS}, e.g. `openssl rand -hex 32`)')
    return text


def new_key() -> bytes:
    return secrets.token_hex(32).encode()


def parse_address(text: str):
    """'HOST:PORT' -> (host, port), with a clear error."""
    host, sep, port = str(text).rpartition(':')
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise UserError(f'bad address {text!r}: expected HOST:PORT, e.g. 10.0.0.5:7450')
    return host.strip('[]'), int(port)


# ---- framing ----------------------------------------------------------------------------------
def _recv_exact(sock, n):
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            raise EOFError('control channel closed')
        buf += chunk
    return bytes(buf)


def _mac(key, *parts):
    return hmac.new(key, b''.join(parts), hashlib.sha256).digest()


class Channel:
    """One authenticated connection: send()/recv() of picklable objects, close(). Sending is
    thread-safe; one thread receives."""

    def __init__(self, sock, session_key: bytes, is_server: bool, peer: str = ''):
        self.sock = sock
        self.peer = peer
        self._key = session_key
        self._out_dir, self._in_dir = (b'c>w', b'w>c') if is_server else (b'w>c', b'c>w')
        self._out_seq = 0
        self._in_seq = 0
        self._lock = threading.Lock()

    def send(self, obj):
        payload = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:
            tag = _mac(self._key, self._out_dir, struct.pack('>Q', self._out_seq), payload)
            self._out_seq += 1
            self.sock.sendall(struct.pack('>I', len(payload)) + tag + payload)

    def recv(self, timeout=None):
        """The next message; EOFError when the peer closed, socket.timeout when nothing came
        within `timeout`, AuthError (the connection is closed) on a bad tag."""
        self.sock.settimeout(timeout)
        (n,) = struct.unpack('>I', _recv_exact(self.sock, 4))
        if n > MAX_FRAME:
            self.close()
            raise AuthError(f'control frame of {n} bytes from {self.peer}')
        tag = _recv_exact(self.sock, TAG)
        payload = _recv_exact(self.sock, n)
        expected = _mac(self._key, self._in_dir, struct.pack('>Q', self._in_seq), payload)
        if not hmac.compare_digest(tag, expected):
            self.close()
            raise AuthError(f'control frame from {self.peer} failed authentication')
        self._in_seq += 1
        return pickle.loads(payload)      # only after its tag matched

    def close(self):
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    @property
    def is_tcp(self):
        return self.sock.family != socket.AF_UNIX


# ---- handshake --------------------------------------------------------------------------------
def server_handshake(sock, key: bytes, peer='') -> Channel:
    sock.settimeout(HANDSHAKE_TIMEOUT_S)
    s_nonce = secrets.token_bytes(NONCE)
    sock.sendall(MAGIC + s_nonce)
    c_nonce = _recv_exact(sock, NONCE)
    proof = _recv_exact(sock, TAG)
    if not hmac.compare_digest(proof, _mac(key, b'worker', s_nonce, c_nonce)):
        try:
            sock.sendall(REFUSED)
        except OSError:
            pass
        sock.close()
        raise AuthError(f'refused a worker from {peer or "?"}: it does not know the control key')
    sock.sendall(ACCEPTED + _mac(key, b'coordinator', c_nonce, s_nonce))
    sock.settimeout(None)
    return Channel(sock, _mac(key, b'session', s_nonce, c_nonce), True, peer)


def client_handshake(sock, key: bytes, peer='') -> Channel:
    sock.settimeout(HANDSHAKE_TIMEOUT_S)
    head = _recv_exact(sock, len(MAGIC) + NONCE)
    if not head.startswith(MAGIC):
        sock.close()
        raise AuthError(f'{peer} is not an ego-motion coordinator\'s control channel')
    s_nonce = head[len(MAGIC):]
    c_nonce = secrets.token_bytes(NONCE)
    sock.sendall(c_nonce + _mac(key, b'worker', s_nonce, c_nonce))
    try:
        verdict = _recv_exact(sock, 1)
    except EOFError:
        verdict = REFUSED
    if verdict != ACCEPTED:
        sock.close()
        raise AuthError(f'coordinator at {peer} refused this worker: wrong control key')
    proof = _recv_exact(sock, TAG)
    if not hmac.compare_digest(proof, _mac(key, b'coordinator', c_nonce, s_nonce)):
        sock.close()
        raise AuthError(f'{peer} does not know the control key: not our coordinator')
    sock.settimeout(None)
    return Channel(sock, _mac(key, b'session', s_nonce, c_nonce), False, peer)


# ---- listeners and connecting ------------------------------------------------------------------
class Listener:
    """accept() -> an authenticated Channel; AuthError for a peer without the key."""

    def __init__(self, sock, key: bytes, address):
        self.sock, self.key, self.address = sock, key, address

    def accept(self) -> Channel:
        conn, addr = self.sock.accept()
        peer = addr if isinstance(addr, str) and addr else (
            f'{addr[0]}:{addr[1]}' if isinstance(addr, tuple) else 'local')
        if conn.family != socket.AF_UNIX:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            return server_handshake(conn, self.key, peer)
        except (EOFError, OSError) as e:
            if isinstance(e, AuthError):
                raise
            conn.close()
            raise AuthError(f'handshake with {peer} failed: {e}') from None

    def close(self):
        self.sock.close()
        if isinstance(self.address, str) and os.path.exists(self.address):
            os.unlink(self.address)


def listen(directory, key: bytes = None):
    """A listener on a fresh Unix socket in `directory`; returns (listener, env for the
    workers it starts: the key, which they remove from their environment)."""
    key = key or new_key()
    address = os.path.join(str(directory), f'control_{os.getpid()}_{secrets.token_hex(3)}.sock')
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(address)
    os.chmod(address, 0o600)
    sock.listen(16)
    return Listener(sock, key, address), {KEY_ENV: key.decode()}


def listen_tcp(address: str, key: bytes) -> Listener:
    host, port = parse_address(address)
    family = socket.AF_INET6 if ':' in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise UserError(f'cannot listen for workers on {address}: {e.strerror}') from None
    sock.listen(16)
    return Listener(sock, key, sock.getsockname()[:2])


def connect(address, key: bytes = None) -> Channel:
    """A local worker: `address` is the coordinator's Unix socket, the key in the
    environment (removed: nothing the worker starts inherits it)."""
    key = key or os.environ.pop(KEY_ENV).encode()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.connect(address)
    return client_handshake(sock, key, address)


def connect_tcp(address: str, key: bytes, timeout=HANDSHAKE_TIMEOUT_S) -> Channel:
    host, port = parse_address(address)
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as e:
        raise ConnectionError(f'cannot reach the coordinator at {address}: {e.strerror or e}') from None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return client_handshake(sock, key, address)


def keep_alive(channel: Channel, stopped: threading.Event, period_s=HEARTBEAT_S):
    """A thread that sends PING every `period_s` until `stopped` or the channel fails."""
    def run():
        while not stopped.wait(period_s):
            try:
                channel.send((PING,))
            except (OSError, ValueError):
                return
    t = threading.Thread(target=run, daemon=True, name='control-heartbeat')
    t.start()
    return t
