"""Per-edge frame authentication: hash-then-MAC, one keyed BLAKE2b tag per receiving neighbour.

Sans-IO: keys and bytes in, tags and booleans out. The launcher draws one random *fleet secret*;
the key of the communication edge {i, j} is ``k_ij = BLAKE2b(pack(min, max), key=secret,
person="shapefleet-edge1")``. A robot holds only the keys of its own edges (its per-robot fleet
file carries nothing else). A frame body is hashed once, ``D = BLAKE2b-256(frame,
person="shapefleet-body2")``, and tagged once per neighbour j with
``BLAKE2b(pack(sender, receiver) || D, key=k_ij, digest_size=16, person="shapefleet-tag2")``:
the sender hashes the ~38 KB body once for all its neighbours (not once per neighbour), a
receiver once per frame, and each tag is a keyed hash of 40 bytes. So

* a process that knows the fleet id and everything shared in the fleet files, but no edge key,
  cannot make a frame any robot accepts: the keyed hash is a PRF/MAC on (sender, receiver, D),
  and a frame other than the tagged one with the same D would be a collision of BLAKE2b-256
  (~2^128 work) -- the same argument as a MAC over the whole body, with collision resistance of
  the 256-bit body digest added;
* a robot i (or a stolen per-robot file of i) can forge frames "from j" only towards i itself,
  never towards a third robot k (it lacks k_jk);
* the (sender, receiver) pair inside the MAC stops a tag from being reflected back or moved to
  another edge.

The person strings separate the body digest from the tag, the edge keys and the config tag, and
from the earlier scheme (person "shapefleet-tag1", a keyed hash over the whole body): a tag of
that scheme never verifies here (rejected as ``auth``).

Why per-edge symmetric keys rather than per-robot keys: with a symmetric MAC, whoever can verify
j's frames can also forge them, so per-robot keys shared with neighbours would let any neighbour
of j speak for j to every other neighbour of j. Per-edge keys close that at the cost of one
16-byte tag per neighbour in each frame (robots have few neighbours). See docs/protocol.md.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import struct
from collections.abc import Iterable, Mapping
from typing import Any

from protocol.keys import validate_robot_id

FLEET_SECRET_BYTES = 32
EDGE_KEY_BYTES = 32
TAG_BYTES = 16
BODY_DIGEST_BYTES = 32
_EDGE_PERSON = b"shapefleet-edge1"
_BODY_PERSON = b"shapefleet-body2"
_TAG_PERSON = b"shapefleet-tag2"


def new_fleet_secret() -> bytes:
    """A fresh random fleet secret (the launcher draws one per fleet it writes)."""
    return secrets.token_bytes(FLEET_SECRET_BYTES)


def _check_key(name: str, key: object, size: int) -> bytes:
    if not isinstance(key, (bytes, bytearray)) or len(key) != size:
        raise ValueError(f"{name} must be {size} bytes")
    return bytes(key)


def edge_key(secret: bytes, i: int, j: int) -> bytes:
    """The key of the undirected edge {i, j}, derived from the fleet secret."""
    secret = _check_key("fleet secret", secret, FLEET_SECRET_BYTES)
    a, b = sorted((validate_robot_id(i), validate_robot_id(j)))
    if a == b:
        raise ValueError(f"no edge from robot {a} to itself")
    return hashlib.blake2b(
        struct.pack("<II", a, b), key=secret, digest_size=EDGE_KEY_BYTES, person=_EDGE_PERSON
    ).digest()


def body_digest(body: bytes) -> bytes:
    """D, the 32-byte digest of a frame body every tag of it covers: computed once per body."""
    return hashlib.blake2b(body, digest_size=BODY_DIGEST_BYTES, person=_BODY_PERSON).digest()


def frame_tag(key: bytes, sender: int, receiver: int, body: bytes) -> bytes:
    """The 16-byte tag of ``body`` sent by ``sender`` to ``receiver`` under their edge key."""
    return digest_tag(key, sender, receiver, body_digest(body))


def digest_tag(key: bytes, sender: int, receiver: int, digest: bytes) -> bytes:
    """The tag of the body whose :func:`body_digest` is ``digest``."""
    h = _edge_hasher(key, sender, receiver)
    h.update(digest)
    return h.digest()


def _edge_hasher(key: bytes, sender: int, receiver: int) -> Any:
    """The state of :func:`digest_tag` before the digest: copied per frame (cheaper than keying anew)."""
    h = hashlib.blake2b(key=key, digest_size=TAG_BYTES, person=_TAG_PERSON)
    h.update(struct.pack("<II", sender, receiver))
    return h


class FrameAuth:
    """One robot's edge keys: tags its frames for each neighbour, verifies theirs to it."""

    def __init__(self, me: int, edge_keys: Mapping[int, bytes]) -> None:
        self.me = validate_robot_id(me)
        self.keys: dict[int, bytes] = {}
        for j, k in edge_keys.items():
            j = validate_robot_id(j)
            if j == self.me:
                raise ValueError(f"robot {me} has no edge key to itself")
            self.keys[j] = _check_key(f"edge key {me}-{j}", k, EDGE_KEY_BYTES)
        # keyed hasher states per direction, ready for the body digest: (me -> j) and (j -> me)
        self._out = {j: _edge_hasher(k, self.me, j) for j, k in self.keys.items()}
        self._in = {j: _edge_hasher(k, j, self.me) for j, k in self.keys.items()}
        # (receiver id as u32 LE, hasher) by receiver id: the envelope's tag entries in order
        self._out_entries = [(struct.pack("<I", j), self._out[j]) for j in sorted(self._out)]

    @classmethod
    def from_secret(cls, secret: bytes, me: int, neighbours: Iterable[int]) -> FrameAuth:
        """Robot ``me``'s keys derived from the fleet secret (only the full fleet file has it)."""
        return cls(me, {j: edge_key(secret, me, j) for j in neighbours})

    @property
    def peers(self) -> frozenset[int]:
        return frozenset(self.keys)

    def tags(self, body: bytes) -> dict[int, bytes]:
        """One tag per neighbour for a frame ``body`` this robot sends (the body hashed once)."""
        digest = body_digest(body)
        out = {}
        for j, base in self._out.items():
            h = base.copy()
            h.update(digest)
            out[j] = h.digest()
        return out

    def tag_entries(self, body: bytes) -> bytes:
        """The tags of :meth:`tags` as an envelope carries them: receiver id (u32 LE) + tag per
        neighbour, by ascending id (built once per sent frame, without the dict and the sort)."""
        return self.digest_tag_entries(body_digest(body))

    def digest_tag_entries(self, digest: bytes) -> bytes:
        """:meth:`tag_entries` of the body whose :func:`body_digest` is ``digest`` (encode_state
        hashes the body itself, once, and keeps D for the receivers of its process)."""
        parts = []
        for prefix, base in self._out_entries:
            h = base.copy()
            h.update(digest)
            parts.append(prefix)
            parts.append(h.digest())
        return b"".join(parts)

    def incoming(self, senders: Iterable[int]) -> dict[int, Any]:
        """The keyed hasher state, ready for the body digest, of each of ``senders`` we share a
        key with: a tag from j to us is ``state.copy()`` fed D (what :meth:`verify_digest` does;
        FrameDecoder's common case does it inline). Copy the states, never feed them."""
        return {j: self._in[j] for j in senders if j in self._in}

    def verify(self, sender: int, body: bytes, tag: bytes) -> bool:
        """True iff ``tag`` is ``sender``'s tag of ``body`` to this robot (constant-time compare)."""
        return self.verify_digest(sender, body_digest(body), tag)

    def verify_digest(self, sender: int, digest: bytes, tag: bytes) -> bool:
        """:meth:`verify` of the body whose :func:`body_digest` is ``digest``."""
        base = self._in.get(sender)
        if base is None or not isinstance(tag, bytes) or len(tag) != TAG_BYTES:
            return False
        h = base.copy()
        h.update(digest)
        return hmac.compare_digest(h.digest(), tag)
