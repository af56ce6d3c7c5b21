"""The coordinator's control channel (coordinator/control.py): authentication, framing, a
dropped connection, key loading. ROS-free: real sockets on localhost."""
import os
import socket
import struct
import threading

import numpy as np
import pytest

from multicam_ego_motion.coordinator import control
from multicam_ego_motion.errors import UserError

KEY = b'0123456789abcdef0123456789abcdef'


def serve_one(listener):
    """Accept one connection in a thread; returns a dict filled with 'conn' or 'error'."""
    out = {}

    def run():
        try:
            out['conn'] = listener.accept()
        except Exception as e:          # the test looks at it
            out['error'] = e
    t = threading.Thread(target=run, daemon=True)
    t.start()
    out['thread'] = t
    return out


@pytest.fixture
def tcp():
    listener = control.listen_tcp('127.0.0.1:0', KEY)
    yield listener, f'127.0.0.1:{listener.address[1]}'
    listener.close()


def test_accepted_and_framed(tcp):
    listener, address = tcp
    side = serve_one(listener)
    client = control.connect_tcp(address, KEY)
    side['thread'].join(5)
    server = side['conn']
    state = {'tracks': np.arange(300_000, dtype=np.float64)}     # a 2.4 MB node state
    client.send((control.SNAPSHOT, 'quarter_cam0_q0', state))
    client.send((control.PING,))
    msg = server.recv(timeout=5)
    assert msg[0] == control.SNAPSHOT and np.array_equal(msg[2]['tracks'], state['tracks'])
    assert server.recv(timeout=5) == (control.PING,)
    server.send((control.STOP,))
    assert client.recv(timeout=5) == (control.STOP,)
    client.close()
    server.close()


def test_wrong_key_refused_on_both_sides(tcp):
    listener, address = tcp
    side = serve_one(listener)
    with pytest.raises(control.AuthError, match='refused this worker: wrong control key'):
        control.connect_tcp(address, b'not-the-key-at-all-0000')
    side['thread'].join(5)
    assert isinstance(side['error'], control.AuthError)
    assert 'does not know the control key' in str(side['error'])


def test_worker_refuses_a_coordinator_without_the_key(tcp):
    """Mutual: a coordinator that only echoes the handshake cannot prove the key."""
    listener, address = tcp
    fake = socket.socket()
    fake.bind(('127.0.0.1', 0))
    fake.listen(1)

    def impostor():
        conn, _ = fake.accept()
        conn.sendall(control.MAGIC + os.urandom(control.NONCE))
        conn.recv(control.NONCE + control.TAG)
        conn.sendall(control.ACCEPTED + os.urandom(control.TAG))
        conn.close()
    threading.Thread(target=impostor, daemon=True).start()
    with pytest.raises(control.AuthError, match='does not know the control key'):
        control.connect_tcp(f'127.0.0.1:{fake.getsockname()[1]}', KEY)
    fake.close()


def test_tampered_or_replayed_frame_is_rejected(tcp):
    listener, address = tcp
    side = serve_one(listener)
    client = control.connect_tcp(address, KEY)
    side['thread'].join(5)
    server = side['conn']
    # a frame with a valid shape but a forged tag: never unpickled
    payload = b'\x80\x05N.'
    client.sock.sendall(struct.pack('>I', len(payload)) + b'\0' * control.TAG + payload)
    with pytest.raises(control.AuthError, match='failed authentication'):
        server.recv(timeout=5)
    client.close()


def test_replayed_frame_is_rejected(tcp):
    listener, address = tcp
    side = serve_one(listener)
    client = control.connect_tcp(address, KEY)
    side['thread'].join(5)
    server = side['conn']
    sent = []
    real = client.sock.sendall
    client.sock = type('Spy', (), {'sendall': lambda self, b: (sent.append(b), real(b))[1]})()
    client.send((control.PING,))
    assert server.recv(timeout=5) == (control.PING,)
    real(sent[0])                      # the same frame again: its sequence number is old
    with pytest.raises(control.AuthError):
        server.recv(timeout=5)


def test_dropped_connection(tcp):
    listener, address = tcp
    side = serve_one(listener)
    client = control.connect_tcp(address, KEY)
    side['thread'].join(5)
    server = side['conn']
    client.close()
    with pytest.raises(EOFError):
        server.recv(timeout=5)
    # silence (a host that died sends no FIN) is a timeout, which the caller turns into a loss
    side = serve_one(listener)
    client = control.connect_tcp(address, KEY)
    side['thread'].join(5)
    with pytest.raises(socket.timeout):
        side['conn'].recv(timeout=0.3)


def test_unix_channel_key_from_environment(tmp_path, monkeypatch):
    listener, env = control.listen(tmp_path)
    side = serve_one(listener)
    monkeypatch.setenv(control.KEY_ENV, env[control.KEY_ENV])
    client = control.connect(listener.address)
    assert control.KEY_ENV not in os.environ          # nothing the worker starts inherits it
    side['thread'].join(5)
    client.send((control.HELLO, 0, 1, 'here'))
    assert side['conn'].recv(timeout=5) == (control.HELLO, 0, 1, 'here')
    assert not side['conn'].is_tcp
    listener.close()
    assert not os.path.exists(listener.address)


def test_key_loading(tmp_path):
    f = tmp_path / 'key'
    f.write_text(KEY.decode() + '\n')
    f.chmod(0o600)
    assert control.load_key(str(f), env={}) == KEY
    assert control.load_key(None, env={control.KEY_ENV: KEY.decode()}) == KEY
    with pytest.raises(UserError, match='no control key'):
        control.load_key(None, env={})
    with pytest.raises(UserError, match='too short'):
        control.load_key(None, env={control.KEY_ENV: 'abc'})
    with pytest.raises(UserError, match='key file .*missing'):
        control.load_key(str(tmp_path / 'missing'), env={})
    with pytest.raises(UserError, match='bad address'):
        control.parse_address('10.0.0.5')
