"""The control channel between the coordinator and its workers.

One Unix-domain socket per coordinator (multiprocessing.connection: length-prefixed pickles,
HMAC handshake with a random key passed in the environment), one connection per worker. Not
ROS: the coordinator must reach a worker whose ROS side is stuck or still starting, and a
node's state (numpy arrays, tracks, landmarks) travels as one pickle, not as a message type.

Messages (tuples):
  worker -> coordinator  (HELLO, index, pid)            once, after connecting
                         (SNAPSHOT, key, state_pickle)  a stateful node finished a frame
                         (REPLY, request_id, dict)      answer to ATTACH / DETACH
  coordinator -> worker  (ATTACH, request_id, node_spec, state_pickle_or_None, wait_links)
                         (DETACH, request_id, key)      reply carries 'state' (a pickle)
                         (LINKS, request_id)            reply when the hosted nodes' links
                                                        inside the graph are matched
                         (STOP,)
"""
import os
import secrets
from multiprocessing.connection import Client, Listener

HELLO, SNAPSHOT, REPLY = 'hello', 'snapshot', 'reply'
ATTACH, DETACH, LINKS, STOP = 'attach', 'detach', 'links', 'stop'
KEY_ENV = 'EGO_MOTION_CONTROL_KEY'


def listen(directory):
    """A listener on a fresh socket in `directory`; returns (listener, env for the workers)."""
    key = secrets.token_bytes(16)
    address = os.path.join(str(directory), f'control_{os.getpid()}_{secrets.token_hex(3)}.sock')
    listener = Listener(address, family='AF_UNIX', authkey=key)
    return listener, {KEY_ENV: key.hex()}


def connect(address):
    key = bytes.fromhex(os.environ.pop(KEY_ENV))     # not inherited by anything the worker starts
    return Client(address, family='AF_UNIX', authkey=key)
