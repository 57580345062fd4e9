"""msgpack codec for the consensus frames robots exchange.

Sans-IO: bytes in, events out, nothing else. :func:`encode_state` turns a :class:`StateUpdate`
into a frame; :class:`FrameDecoder` turns any bytes into either :class:`Decoded` or
:class:`Rejected` and never raises, because a frame is untrusted input from the network and one
malformed frame must not stop a robot. The format and the rejection codes are specified in
``docs/protocol.md``.
"""

from __future__ import annotations

import collections
import hashlib
import hmac
import math
import operator
import struct
import threading
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from agents.messages import MAX_FLAGS, MAX_ROBOT_ID, MAX_ROUND, StateUpdate, check_int, gone_problem
from protocol.auth import TAG_BYTES, FrameAuth, body_digest
from protocol.keys import validate_fleet_id, validate_robot_id

FRAME_VERSION = 1
KIND_STATE = "state"
CONFIG_TAG_SIZE = 8
MAX_FRAME_BYTES = 1 << 20
MAX_SEQ = 2**63 - 1
# Everything of a frame but its two vectors takes < 200 bytes (fleet ids are <= 64 chars).
_FRAME_OVERHEAD_BOUND = 256
MAX_DIM = (MAX_FRAME_BYTES - _FRAME_OVERHEAD_BOUND) // 16

# The checks run in this order; the first that fails names the rejection.
REJECTION_REASONS: tuple[str, ...] = (
    "too-large",        # more than MAX_FRAME_BYTES, refused before unpacking
    "not-msgpack",      # not bytes, not exactly one msgpack object, or beyond the unpack limits
    "not-a-map",        # the object is not a map
    "duplicate-field",  # a key appears twice in the map
    "version",          # "v" is not FRAME_VERSION (checked before the other fields)
    "kind",             # "kind" is not "state"
    "unknown-field",    # a key outside the frame's field set
    "missing-field",    # a field of the frame is absent
    "field-type",       # a field has the wrong msgpack type (bool is not int, str is not bin)
    "fleet",            # another fleet's frame
    "config",           # "cfg" differs: the sender solves a differently configured problem
    "sender",           # "from" is not a known sender (or not the one expected on this key)
    "round",            # round outside [0, 2**31)
    "seq",              # seq outside [0, 2**63)
    "flags",            # flags or pflags outside [0, 2**63)
    "prev",             # prev at round 0, or pflags set without prev
    "vector-length",    # x or prev is not 8 * dim bytes
    "non-finite",       # x or prev holds NaN or +-inf
    "need",             # the optional "need" list names a robot that is not a known sender, twice, or unsorted
    # the optional "gone" / "pgone" lists (robots dropped for good) name a robot that is not a known
    # sender, the sender itself or, per receiver, the receiver; are unsorted; or pgone is not a subset
    # of gone or comes without prev
    "gone",
    # only with authentication (FrameDecoder(auth=...)); "auth" is checked right after unpacking
    # the envelope (before any field of the frame is trusted), "equivocation" last
    "auth",             # no envelope, no tag for this receiver, or a tag that does not verify
    "equivocation",     # a valid frame whose values for a round differ from an earlier one's
)

#: rounds per sender remembered for equivocation (neighbours are at most one round apart)
EQUIVOCATION_WINDOW = 8
_TAG_ENTRY = 4 + TAG_BYTES  # receiver id (u32 LE) + tag
_INT_TYPE = frozenset({int})  # what each item of "need" may be (bool is not int)

_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "v": (int,),
    "kind": (str,),
    "fleet": (str,),
    "from": (int,),
    "round": (int,),
    "seq": (int,),
    "cfg": (bytes,),
    "x": (bytes,),
    "flags": (int,),
    "prev": (bytes, type(None)),
    "pflags": (int,),
}
# Optional fields: absent means "not said" (a frame without one is as valid as before).
# "need": the robots whose value of this frame's round the sender still lacks, sorted ascending
# (protocol/session.py: a neighbour answers a repeat with a fast resend only if it is named).
# "gone" / "pgone": the robots the sender knows to have been dropped for good when it computed x /
# prev (StateUpdate.gone, prev_gone; agents/rounds.py floods them), sorted ascending; absent when
# empty, so a fleet that never loses a robot sends the frames it always sent.
_OPTIONAL_TYPES: dict[str, tuple[type, ...]] = {"need": (tuple,), "gone": (tuple,), "pgone": (tuple,)}
_FIELDS = frozenset(_FIELD_TYPES)
_FIELDS_NEED = _FIELDS | {"need"}
_FIELDS_ALL = _FIELDS | frozenset(_OPTIONAL_TYPES)
MAX_NEED = 1024  # msgpack's array limit of the decoder; a longer list is left out ("not said")


# The message type lives with the algorithms (agents/messages.py): re-exported here so that
# ``from protocol.frames import StateUpdate`` keeps working.
_check_int = check_int


@dataclass(frozen=True)
class Decoded:
    """A frame that passed every check. The receivers of a process share it (protocol/frames.py
    parses a frame once): its arrays are read-only views of the frame's bytes, which numpy
    refuses to make writable, so no receiver can change another's values. ``need``: the robots
    whose value of the frame's round its sender lacked when it sent it (None: not said)."""

    update: StateUpdate
    seq: int
    need: tuple[int, ...] | None = None


@dataclass(frozen=True)
class Rejected:
    """A frame that failed a check: ``reason`` is a code of REJECTION_REASONS, ``detail`` prose."""

    reason: str
    detail: str


def _all_finite(arr: np.ndarray) -> bool:
    """No NaN or inf in ``arr`` (np.count_nonzero: ~2x cheaper than ``.all()``'s Python wrapper,
    and no arithmetic on the values, so no floating-point warning on the frames it rejects)."""
    return bool(np.count_nonzero(np.isfinite(arr)) == arr.size)


def _vector_bytes(name: str, arr: np.ndarray) -> bytes:
    arr = np.asarray(arr)
    if not _all_finite(arr):
        raise ValueError(f"{name} holds non-finite values; no robot would accept the frame")
    # a native little-endian float64 array's bytes are already "<f8" (tobytes: C order, any strides)
    return arr.tobytes() if arr.dtype is _F8 else np.asarray(arr, _F8).tobytes()


_F8 = np.dtype("<f8")  # (a dtype object: np.frombuffer / asarray skip parsing the string, ~0.3 us)
_LOCAL = threading.local()


def _pack(obj: Any) -> bytes:
    """``msgpack.packb(obj, use_bin_type=True)``, the same bytes, by a Packer kept per thread
    (packb makes one per call: ~0.5 us of a frame's ~1.4 us body). A Packer resets its buffer
    after a failed pack, and one thread never packs two objects at once."""
    packer = getattr(_LOCAL, "packer", None)
    if packer is None:
        packer = _LOCAL.packer = msgpack.Packer(use_bin_type=True)
    out: bytes = packer.pack(obj)
    return out


def _check_config_tag(tag: Any) -> bytes:
    if not isinstance(tag, bytes) or len(tag) != CONFIG_TAG_SIZE:
        raise ValueError(f"config_tag must be {CONFIG_TAG_SIZE} bytes (see config_tag())")
    return tag


_FLEETS_SEEN: set[str] = set()  # fleet ids encode_state has validated (a pure check: done once)


def encode_state(
    update: StateUpdate, *, fleet: str, seq: int, config_tag: bytes, auth: FrameAuth | None = None,
    need: Collection[int] | None = None, prime: FrameDecoder | None = None,
) -> bytes:
    """Serialise ``update`` as a version-1 state frame, authenticated when ``auth`` is given.

    ``need``: the robots whose value of ``update.round`` the sender still lacks (written as the
    optional "need" field, sorted; None or more than MAX_NEED robots: left out). It lets a
    neighbour answer a repeat only when the repeat waits for *its* value (docs/protocol.md).

    With ``auth`` (the sender's edge keys) the frame is wrapped in an envelope
    ``[sender, frame, tags]`` carrying one tag per neighbour (docs/protocol.md, "Authentication").
    ``prime``: a decoder of this process (the sender's own, whose way of checking a body its
    neighbours here share): the process's parse memo learns what these bytes parse to from what
    was encoded, so that the receivers of this process do not parse their own process's frames
    (:func:`_prime`; each still authenticates, checks equivocation and dedups them).
    Raises ValueError for anything a receiver would reject (non-finite values, seq out of
    range, bad fleet id or tag, vector longer than MAX_DIM), so such a frame never leaves.
    """
    if type(fleet) is not str or fleet not in _FLEETS_SEEN:  # (a robot sends thousands of frames)
        validate_fleet_id(fleet)
        if len(_FLEETS_SEEN) < 64:
            _FLEETS_SEEN.add(fleet)
    _check_int("seq", seq, MAX_SEQ)
    _check_config_tag(config_tag)
    if update.values.size > MAX_DIM:
        raise ValueError(f"vector of {update.values.size} entries exceeds MAX_DIM={MAX_DIM}")
    frame = {
        "v": FRAME_VERSION,
        "kind": KIND_STATE,
        "fleet": fleet,
        "from": update.sender,
        "round": update.round,
        "seq": seq,
        "cfg": config_tag,
        "x": _vector_bytes("values", update.values),
        "flags": update.flags,
        "prev": (
            None
            if update.prev_values is None
            else _vector_bytes("prev_values", update.prev_values)
        ),
        "pflags": update.prev_flags,
    }
    if need is not None and len(need) <= MAX_NEED:
        frame["need"] = _robot_ids(need)
    if update.gone:  # (StateUpdate checked them: sorted ids, never the sender; pgone within gone)
        if len(update.gone) > MAX_NEED:
            raise ValueError(f"gone names {len(update.gone)} robots, more than a frame holds ({MAX_NEED})")
        frame["gone"] = list(update.gone)
        if update.prev_gone:
            frame["pgone"] = list(update.prev_gone)
    data = _pack(frame)
    if auth is None:
        if prime is not None:
            _prime(prime, frame, data, seq, None)
        return data
    if auth.me != update.sender:
        raise ValueError(f"robot {auth.me}'s keys cannot sign a frame of robot {update.sender}")
    digest = body_digest(data)  # the body hashed once, for every neighbour's tag (protocol/auth.py)
    tags = auth.digest_tag_entries(digest)
    wrapped = _pack([update.sender, data, tags])
    if len(wrapped) > MAX_FRAME_BYTES:
        raise ValueError(f"authenticated frame of {len(wrapped)} bytes exceeds {MAX_FRAME_BYTES}")
    if prime is not None:
        _prime(prime, frame, data, seq, (wrapped, tags), digest)
    return wrapped


def _prime(decoder: FrameDecoder, frame: dict[str, Any], body: bytes, seq: int,
           envelope: tuple[bytes, bytes] | None, digest: bytes | None = None) -> None:
    """Put into the parse memo what ``body`` (and its ``envelope``: the wrapped bytes and the tag
    block) parse to, built from the fields ``encode_state`` packed instead of unpacked again: the
    same entries ``decoder._checked`` and ``_parse_envelope`` would make of those bytes (a valid
    frame: encode_state refused anything a receiver would reject). Only what a receiver looks up
    by the very bytes it got from Zenoh: other bytes miss and are parsed; its own tag is still
    verified, its equivocation and dedup checks still run (branch shell3: the first receiver's
    parse was ~45 us of a frame's ~70 us in a process of 3 robots). ``digest``: the body's
    :func:`body_digest`, which encode_state computed for the tags: kept with the envelope, so
    that the receivers here check their tags without hashing the body again (a pure function of
    the body bytes the entry is found by, like the parse)."""
    x, prev, need, sender = frame["x"], frame["prev"], frame.get("need"), frame["from"]
    parsed = _body_of(sender, frame["round"], seq, frame["flags"], x, prev, frame["pflags"],
                      None if need is None else tuple(need), _read_only(x), None if prev is None else _read_only(prev),
                      tuple(frame.get("gone", ())), tuple(frame.get("pgone", ())),
                      valid=True)
    if envelope is None:
        _MEMO.put((decoder._profile, sender, body), parsed, len(body))
    else:  # receivers look the envelope up and find the body's parse in it: the body's own entry
        wrapped, raw = envelope  # would only be reached once the envelope's was evicted (it goes first)
        env = _Envelope(sender, body, dict(_TAG_ENTRY_STRUCT.iter_unpack(raw)))
        env.parsed[decoder._profile] = parsed
        env.digest = digest
        _MEMO.put(wrapped, env, len(wrapped))


def _robot_ids(ids: Collection[int]) -> list[int]:
    """``ids`` sorted, each checked by validate_robot_id -- at once when they are all ints in
    range (a sent frame names up to 31 here, every frame of a 32-robot fleet)."""
    out = sorted(ids) if _INT_TYPE.issuperset(map(type, ids)) else []
    if len(out) != len(ids) or (out and not (0 <= out[0] and out[-1] <= MAX_ROBOT_ID)):
        out = sorted(validate_robot_id(j) for j in ids)  # (raises, naming the bad one)
    return out


_CONFIG_PERSON = b"shapefleet-cfg1"


def _feed(h: Any, part: Any) -> None:
    """Canonical, type-tagged, length-prefixed bytes of one part (see config_tag)."""

    def length(n: int) -> bytes:
        return struct.pack("<Q", n)

    if part is None:
        h.update(b"N")
    elif isinstance(part, (bool, np.bool_)):
        h.update(b"B1" if part else b"B0")
    elif isinstance(part, (int, np.integer)):
        digits = str(int(part)).encode()
        h.update(b"I" + length(len(digits)) + digits)
    elif isinstance(part, (float, np.floating)):
        value = float(part)
        if math.isnan(value):
            raise ValueError("config_tag: NaN has no stable fingerprint")
        if value.is_integer():  # 2 and 2.0 describe the same configuration
            _feed(h, int(value))
        else:
            h.update(b"F" + struct.pack("<d", value))
    elif isinstance(part, str):
        data = part.encode("utf-8")
        h.update(b"S" + length(len(data)) + data)
    elif isinstance(part, (bytes, bytearray, memoryview)):
        data = bytes(part)
        h.update(b"Y" + length(len(data)) + data)
    elif isinstance(part, np.ndarray):
        if part.dtype.kind not in "biuf":
            raise TypeError(f"config_tag: cannot fingerprint an array of dtype {part.dtype}")
        arr = part.astype("<f8") + 0.0  # + 0.0 turns -0.0 into 0.0
        if np.isnan(arr).any():
            raise ValueError("config_tag: NaN has no stable fingerprint")
        h.update(b"A" + length(arr.ndim) + b"".join(length(n) for n in arr.shape))
        h.update(np.ascontiguousarray(arr).tobytes())
    elif isinstance(part, (list, tuple)):
        h.update(b"L" + length(len(part)))
        for item in part:
            _feed(h, item)
    else:
        raise TypeError(f"config_tag: cannot fingerprint a {type(part).__name__}")


def config_tag(*parts: Any) -> bytes:
    """8-byte fingerprint of a problem configuration, identical on every machine.

    Robots whose tags differ reject each other's frames instead of mixing iterates of different
    problems. Parts may be None, bool, int, float, str, bytes, numpy arrays (hashed as shape plus
    little-endian float64 values) and lists/tuples of these. Numbers are fingerprinted by value,
    so ``2``, ``2.0`` and ``np.int64(2)`` agree; a bool is not a number and a list is not an array.
    NaN is refused (ValueError), other types raise TypeError.
    """
    h = hashlib.blake2b(digest_size=CONFIG_TAG_SIZE, person=_CONFIG_PERSON)
    _feed(h, list(parts))
    return h.digest()


class _Reject(Exception):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(reason, detail)
        self.reason = reason
        self.detail = detail


class _Envelope:
    """An authentication envelope's structure (nothing verified yet), shared by the receivers of
    a process: sender, body, the tag of each receiver (the first one a receiver has), and the
    body's checked fields by decoder profile, filled by the first receiver that verified its tag
    (FrameDecoder._decode). ``digest``: the body's :func:`body_digest` once a receiver of the
    process (or encode_state's prime) computed it -- a pure function of the body, so each body is
    hashed once per process however many of its robots check their tags (:meth:`body_digest`)."""

    __slots__ = ("sender", "body", "tags", "parsed", "digest")

    def __init__(self, sender: int, body: bytes, tags: dict[int, bytes]) -> None:
        self.sender, self.body, self.tags = sender, body, tags
        self.parsed: dict[int, _Body] = {}
        self.digest: bytes | None = None

    def body_digest(self) -> bytes:
        """D of the body (protocol/auth.py), computed on first use (two threads may both compute
        it: the same bytes)."""
        digest = self.digest
        if digest is None:
            digest = self.digest = body_digest(self.body)
        return digest


def _parse_envelope(data: Any) -> _Envelope:
    """The structure of an authentication envelope; "auth" if it is not one."""
    env = FrameDecoder._unpack_object(data)
    if isinstance(env, list):  # a map: a bare, unauthenticated version-1 frame
        raise _Reject("auth", "frame is not authenticated (no envelope)")
    if not (
        isinstance(env, tuple)
        and len(env) == 3
        and type(env[0]) is int
        and type(env[1]) is bytes
        and type(env[2]) is bytes
        and len(env[2]) % _TAG_ENTRY == 0
    ):
        raise _Reject("auth", "malformed authentication envelope")
    sender, body, raw = env
    tags: dict[int, bytes] = dict(_TAG_ENTRY_STRUCT.iter_unpack(raw))
    if len(tags) * _TAG_ENTRY != len(raw):  # a receiver named twice: its first tag counts
        tags = {}
        for j, tag in _TAG_ENTRY_STRUCT.iter_unpack(raw):
            tags.setdefault(j, tag)
    return _Envelope(sender, body, tags)


_TAG_ENTRY_STRUCT = struct.Struct(f"<I{TAG_BYTES}s")  # one entry of the tag block: receiver id, tag


class _Body:
    """A frame body that passed every check, as the receivers of a process share it: its sender
    and round, the one :class:`Decoded` every receiver gets (its arrays are read-only views of
    the frame's immutable bytes, so no receiver can change what another one holds), and the
    equivocation claims (flags, raw x) / (pflags, raw prev), built once instead of per receiver."""

    __slots__ = ("sender", "round", "decoded", "claim", "prev_claim", "gone")

    def __init__(self, decoded: Decoded, x: bytes, prev: bytes | None) -> None:
        update = decoded.update
        self.sender, self.round, self.decoded = update.sender, update.round, decoded
        # (the robots dropped for good are part of a round's claim once there are any: a frame is
        # the sender's word on both; none, the claims stay what they were)
        gone, pgone = update.gone, update.prev_gone
        self.gone = frozenset(gone) if gone else None  # (pgone is within gone: checked)
        self.claim = (update.flags, x) if not gone else (update.flags, x, gone)
        self.prev_claim = None if prev is None else (update.prev_flags, prev) if not pgone else (
            update.prev_flags, prev, pgone)


class _ParseMemo:
    """Parsed frames by their bytes, so that a frame many receivers get is parsed once.

    A broadcast frame reaches every neighbour: in one process (robots sharing a Zenoh session,
    or the in-process fleet) each used to unpack and check the same bytes again -- the largest
    cost of a round in a big fleet (32 robots: ~55 % of the in-process fleet's time). Parsing is
    a pure function of the bytes (and of the decoder's fleet, senders, dimension and config,
    which are part of the key), so a hit gives exactly what a parse would: the fields, or the
    same rejection. Per-receiver work (its tag, equivocation, fresh arrays) is never memoised.
    Bounded in entries and bytes, oldest out first. Only ``bytes`` data are memoised (hashable,
    immutable); the key is the data itself (an envelope) or a tuple ending with it (a body).
    """

    def __init__(self, max_entries: int = 4096, max_bytes: int = 32 << 20) -> None:
        self.max_entries, self.max_bytes = max_entries, max_bytes
        self._items: dict[Any, Any] = {}
        # keys oldest first: next(iter(dict)) after many pops from the front scans the dict's
        # deleted slots (py-spy, 32-robot in-process run: get_or_parse's own share 2.6 % -> 1.3 %)
        self._order: collections.deque[Any] = collections.deque()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get_or_parse(self, key: Any, data: Any, parse: Any) -> Any:
        """``parse(data)`` (or the ``_Reject`` it raised) for ``key``, computed once."""
        if type(data) is not bytes:
            return parse(data)
        found = self._items.get(key)
        if found is None:
            self.misses += 1
            try:
                found = (True, parse(data), len(data))
            except _Reject as r:
                found = (False, (r.reason, r.detail), len(data))
            self._add(key, found)
        else:
            self.hits += 1
        if not found[0]:
            raise _Reject(*found[1])
        return found[1]

    def put(self, key: Any, value: Any, size: int) -> None:
        """Remember ``value`` as what the ``size`` bytes of ``key`` parse to (encode_state's prime)."""
        self._add(key, (True, value, size))

    def _add(self, key: Any, found: tuple[bool, Any, int]) -> None:
        with self._lock:  # robots of several threads may share it: evict consistently
            if key not in self._items:
                self._items[key] = found
                self._order.append(key)
                self._bytes += found[2]
            while len(self._items) > self.max_entries or self._bytes > self.max_bytes:
                self._bytes -= self._items.pop(self._order.popleft())[2]


_MEMO = _ParseMemo()
_compare_digest = hmac.compare_digest


def _body_of(sender: int, rnd: int, seq: int, flags: int, x: bytes, prev: bytes | None, pflags: int,
             need: tuple[int, ...] | None, values: np.ndarray, prev_values: np.ndarray | None,
             gone: tuple[int, ...] = (), pgone: tuple[int, ...] = (), *, valid: bool = False) -> _Body:
    """The shared parse of a checked frame body (its fields, the vectors as read-only arrays).
    ``valid``: the fields are those of a StateUpdate that passed its checks (encode_state's prime),
    so they are not checked again where the vectors are already native float64 (little-endian hosts)."""
    if valid and _NATIVE_F8:
        update = object.__new__(StateUpdate)  # (a frozen dataclass: its fields set as __init__ would)
        update.__dict__.update(sender=sender, round=rnd, values=values, flags=flags, prev_values=prev_values,
                               prev_flags=pflags, gone=gone, prev_gone=pgone)
        decoded = object.__new__(Decoded)  # (likewise: a frozen dataclass's __init__ is ~0.4 us of setattrs)
        decoded.__dict__.update(update=update, seq=seq, need=need)
        return _Body(decoded, x, prev)
    update = StateUpdate(  # validated once here; every receiver of the process gets this one
        sender=sender,
        round=rnd,
        values=values,
        flags=flags,
        prev_values=prev_values,
        prev_flags=pflags,
        gone=gone,
        prev_gone=pgone,
    )
    if update.values is not values:  # (a big-endian machine: as_vector made a native copy)
        for arr in (update.values, update.prev_values):
            if arr is not None:
                arr.flags.writeable = False
    return _Body(Decoded(update, seq, need), x, prev)


_NATIVE_F8 = np.dtype("<f8").isnative  # frames' vectors are float64 as this host holds them


def _read_only(raw: bytes) -> np.ndarray:
    """The float64 vector of a frame's raw little-endian bytes, as a view of those (immutable)
    bytes: read-only, and numpy refuses to make it writable again (``flags.writeable = True``
    raises), so the receivers of a process can share it -- no robot can change another's values."""
    return np.frombuffer(raw, _F8)


# (fleet, senders, dim, config tag) -> a small int naming that way of checking a body
_PROFILES: dict[tuple[Any, ...], int] = {}


class FrameDecoder:
    """Validates frames for one robot: its fleet, its neighbours, its vector length, its problem.

    Without ``auth`` it is stateless apart from counters: deduplication and round bookkeeping
    belong to the algorithm state machine, which sees ``Decoded.update.round`` and ``Decoded.seq``.
    With ``auth`` (this robot's edge keys) only authenticated frames pass, and the decoder
    remembers each sender's values of its last EQUIVOCATION_WINDOW rounds to refuse a second,
    different frame for a round it has already accepted (equivocation); retransmissions of the
    same values pass.
    """

    def __init__(
        self,
        fleet: str,
        known_senders: Collection[int],
        dim: int,
        config_tag: bytes,
        auth: FrameAuth | None = None,
        receiver: int | None = None,
    ) -> None:
        self.fleet = validate_fleet_id(fleet)
        self.known_senders = frozenset(validate_robot_id(s) for s in known_senders)
        if type(dim) is not int or not 1 <= dim <= MAX_DIM:
            raise ValueError(f"dim must be an int in [1, {MAX_DIM}], got {dim!r}")
        self.dim = dim
        self.config_tag = _check_config_tag(config_tag)
        self.counts: collections.Counter[str] = collections.Counter()
        self.accepted = 0
        self.auth = auth
        # sender -> round -> (flags, raw float64 bytes) of the first valid frame seen
        self._seen: dict[int, dict[int, tuple[int, bytes]]] = {}
        self._seen_top: dict[int, int] = {}  # sender -> the newest round in _seen[sender]
        # decoders that check a body alike (same fleet, senders, dim, config) share parsed bodies
        self._profile = _PROFILES.setdefault((self.fleet, self.known_senders, dim, self.config_tag), len(_PROFILES))
        # decode's common case: keyed hasher states of the known senders we share a key with
        self._in = None if auth is None else auth.incoming(self.known_senders)
        self._me = None if auth is None else auth.me
        # the robot these frames are for (default: the keys' owner): a frame saying it was dropped
        # for good is refused ("gone") -- it is here, so the sender's problem is not the fleet's
        self.receiver = receiver if receiver is not None else self._me

    def decode(self, data: bytes, *, expected_sender: int | None = None) -> Decoded | Rejected:
        """Check ``data`` completely; never raises.

        ``expected_sender``, when given (e.g. the robot id in the key the frame arrived on),
        must equal the frame's "from" field, so a robot cannot speak for another.
        """
        ins = self._in
        if ins is not None and type(data) is bytes:
            # The common case, inline: a frame another receiver of this process has already opened
            # and parsed (every receiver of a broadcast but the first), whose sender is the
            # expected one, a known sender with whom we share a key, and whose tag to us verifies
            # (FrameAuth.verify_digest's work on the body digest the envelope holds: the receiver
            # that parsed it, or the sender here, computed it; the tags of a parsed envelope are
            # TAG_BYTES bytes each). Anything else -- including a tag that does not verify -- takes
            # the full path below, which gives the verdict.
            found = _MEMO._items.get(data)
            if found is not None and found[0] and len(data) <= MAX_FRAME_BYTES:
                env = found[1]
                base = ins.get(expected_sender) if env.sender == expected_sender else None
                body = env.parsed.get(self._profile)
                tag = env.tags.get(self._me)
                if base is not None and body is not None and tag is not None:
                    h = base.copy()
                    h.update(env.body_digest())
                    if _compare_digest(h.digest(), tag):
                        _MEMO.hits += 1
                        try:
                            if body.gone is not None:
                                self._check_receiver(body)
                            self._check_equivocation(body)
                        except _Reject as r:
                            self.counts[r.reason] += 1
                            return Rejected(r.reason, r.detail)
                        self.accepted += 1
                        return body.decoded
        try:
            result: Decoded | Rejected = self._decode(data, expected_sender)
        except _Reject as r:
            result = Rejected(r.reason, r.detail)
            self.counts[r.reason] += 1
        else:
            self.accepted += 1
        return result

    def _decode(self, data: Any, expected_sender: int | None) -> Decoded:
        if type(data) is bytes:
            size = len(data)
        elif isinstance(data, (bytearray, memoryview)):
            size = memoryview(data).nbytes
        else:
            raise _Reject("not-msgpack", f"expected bytes, got {type(data).__name__}")
        if size > MAX_FRAME_BYTES:
            raise _Reject("too-large", f"{size} bytes > {MAX_FRAME_BYTES}")
        if self.auth is None:
            body = self._parsed_frame(data, expected_sender)
            if body.gone is not None:
                self._check_receiver(body)
            return body.decoded
        env = self._open_envelope(data, expected_sender)
        body = env.parsed.get(self._profile)
        if body is None:  # the first receiver of this frame here: parse (or the memo's rejection)
            body = env.parsed[self._profile] = self._parsed_frame(env.body, env.sender)
        if body.gone is not None:
            self._check_receiver(body)
        self._check_equivocation(body)
        return body.decoded

    def _check_receiver(self, body: _Body) -> None:
        """Refuse a frame that says this receiver was dropped for good (per receiver: the parse is shared)."""
        if self.receiver is not None and body.gone is not None and self.receiver in body.gone:
            raise _Reject("gone", f"sender {body.sender} says robot {self.receiver}, the receiver, was dropped for good")

    def _open_envelope(self, data: Any, expected_sender: int | None) -> _Envelope:
        """The authenticated frame's envelope (shared, see _Envelope); "auth" unless the tag to
        us verifies."""
        auth = self.auth
        assert auth is not None
        found = _MEMO._items.get(data) if type(data) is bytes else None
        if found is not None and found[0]:  # the memo's hit path, inline: every receiver but one takes it
            _MEMO.hits += 1
            env: _Envelope = found[1]
        else:
            env = _MEMO.get_or_parse(data, data, _parse_envelope)
        sender = env.sender
        if sender not in self.known_senders:
            raise _Reject("sender", f"sender {sender} is not a known sender")
        if expected_sender is not None and sender != expected_sender:
            raise _Reject("sender", f"sender {sender} on robot {expected_sender}'s key")
        if sender not in auth.keys:
            raise _Reject("auth", f"no key shared with sender {sender} (not a neighbour)")
        tag = env.tags.get(auth.me)
        if tag is None:
            raise _Reject("auth", f"no tag for robot {auth.me} in sender {sender}'s frame")
        if not auth.verify_digest(sender, env.body_digest(), tag):
            raise _Reject("auth", f"tag of sender {sender}'s frame does not verify")
        return env

    def _parsed_frame(self, data: Any, expected_sender: int | None) -> _Body:
        """The checked fields of a frame body and a StateUpdate built from them (memoised: the
        robots of a process, and every receiver of the in-process fleet, parse each distinct
        frame once)."""
        return _MEMO.get_or_parse((self._profile, expected_sender, data), data,
                                  lambda d: self._checked(d, expected_sender))

    def _checked(self, data: Any, expected_sender: int | None) -> _Body:
        return _body_of(*self._decode_fields(data, expected_sender))

    def _check_equivocation(self, body: _Body) -> None:
        """Refuse a frame whose values of a round differ from those first accepted; then remember
        (the claims (flags, raw little-endian float64 bytes) of the sender's last
        EQUIVOCATION_WINDOW rounds: rounds up to its newest - EQUIVOCATION_WINDOW are forgotten)."""
        sender, rnd = body.sender, body.round
        seen = self._seen.get(sender)
        claim, prev_claim = body.claim, body.prev_claim
        if (seen is not None and rnd not in seen and self._seen_top.get(sender) == rnd - 1
                and prev_claim is not None and seen.get(rnd - 1) == prev_claim):
            # the common case (most frames): the sender's next round, whose values of its last
            # round are the ones we hold -- what the general rule below does then, in short
            seen[rnd] = claim
            self._seen_top[sender] = rnd
            seen.pop(rnd - EQUIVOCATION_WINDOW, None)
            return
        if seen is None:
            seen = self._seen[sender] = {}
        first = seen.get(rnd)
        if first is not None and first != claim:
            raise _Reject("equivocation", f"sender {sender} sent two different frames for round {rnd}")
        prev_first = None if prev_claim is None else seen.get(rnd - 1)
        if prev_first is not None and prev_first != prev_claim:
            raise _Reject("equivocation", f"sender {sender} sent two different frames for round {rnd - 1}")
        if first is not None and (prev_claim is None or prev_first is not None):
            return  # nothing new to remember (a copy, or a frame every receiver gets once more)
        top = self._seen_top.get(sender, -1)  # the newest round remembered (never forgotten)
        new_top = rnd if rnd > top else top
        oldest_kept = new_top - EQUIVOCATION_WINDOW  # rounds up to this one are forgotten
        if first is None and rnd > oldest_kept:
            seen[rnd] = claim
        if prev_claim is not None and prev_first is None and rnd - 1 > oldest_kept:
            seen[rnd - 1] = prev_claim
        if new_top > top:
            self._seen_top[sender] = new_top
            if new_top - top <= EQUIVOCATION_WINDOW:  # forget the rounds that left the window
                for r in range(top - EQUIVOCATION_WINDOW + 1, oldest_kept + 1):
                    seen.pop(r, None)
            else:
                for r in [r for r in seen if r <= oldest_kept]:
                    del seen[r]

    def _decode_fields(self, data: Any, expected_sender: int | None) -> tuple[Any, ...]:
        """Every check of a frame body; its fields (sender, round, seq, flags, x, prev, pflags,
        need) with the vectors as raw little-endian bytes, then the vectors as read-only arrays."""
        frame = self._unpack(data)
        self._check_version_and_kind(frame)
        keys = frame.keys()
        if keys != _FIELDS_NEED and keys != _FIELDS and not (_FIELDS <= keys <= _FIELDS_ALL):  # (the common two first)
            unknown = [k for k in frame if k not in _FIELD_TYPES and k not in _OPTIONAL_TYPES]
            if unknown:
                raise _Reject("unknown-field", f"unknown field(s) {sorted(map(repr, unknown))}")
            missing = [k for k in _FIELD_TYPES if k not in frame]
            if missing:
                raise _Reject("missing-field", f"missing field(s) {missing}")
        for name, types in _FIELD_TYPES.items():
            if type(frame[name]) not in types:
                raise _Reject(
                    "field-type", f"{name!r} has type {type(frame[name]).__name__}"
                )
        need = frame.get("need")
        if need is not None:
            if type(need) not in _OPTIONAL_TYPES["need"] or not _INT_TYPE.issuperset(map(type, need)):
                raise _Reject("field-type", "'need' is not an array of ints")
        gone = pgone = ()
        if "gone" in frame or "pgone" in frame:  # (only after a loss: most frames skip this)
            gone, pgone = frame.get("gone", ()), frame.get("pgone", ())
            for name, ids in (("gone", gone), ("pgone", pgone)):
                if type(ids) is not tuple or not _INT_TYPE.issuperset(map(type, ids)):
                    raise _Reject("field-type", f"{name!r} is not an array of ints")

        if frame["fleet"] != self.fleet:
            raise _Reject("fleet", f"frame of fleet {frame['fleet'][:80]!r}, not {self.fleet!r}")
        if frame["cfg"] != self.config_tag:
            raise _Reject(
                "config",
                f"config tag {frame['cfg'].hex()} != {self.config_tag.hex()}",
            )
        sender = frame["from"]
        if sender not in self.known_senders:
            raise _Reject("sender", f"sender {sender} is not a known sender")
        if expected_sender is not None and sender != expected_sender:
            raise _Reject("sender", f"sender {sender} on robot {expected_sender}'s key")
        if not 0 <= frame["round"] <= MAX_ROUND:
            raise _Reject("round", f"round {frame['round']} outside [0, {MAX_ROUND}]")
        if not 0 <= frame["seq"] <= MAX_SEQ:
            raise _Reject("seq", f"seq {frame['seq']} outside [0, {MAX_SEQ}]")
        for name in ("flags", "pflags"):
            if not 0 <= frame[name] <= MAX_FLAGS:
                raise _Reject("flags", f"{name} {frame[name]} outside [0, {MAX_FLAGS}]")
        if frame["prev"] is not None and frame["round"] == 0:
            raise _Reject("prev", "prev present at round 0")
        if frame["prev"] is None and frame["pflags"] != 0:
            raise _Reject("prev", "pflags set without prev")

        values = self._vector("x", frame["x"])
        prev_values = None if frame["prev"] is None else self._vector("prev", frame["prev"])
        if need is not None:
            known = self.known_senders
            if not known.issuperset(need) or not all(map(operator.lt, need, need[1:])):
                raise _Reject("need", f"'need' {list(need)[:8]!r} names an unknown robot, or is not sorted")
        if gone or pgone:
            self._check_gone(sender, gone, pgone, frame["prev"] is not None)
        return (sender, frame["round"], frame["seq"], frame["flags"], frame["x"], frame["prev"], frame["pflags"],
                need, values, prev_values, gone, pgone)

    def _check_gone(self, sender: int, gone: tuple[int, ...], pgone: tuple[int, ...], has_prev: bool) -> None:
        """The robots a frame says were dropped for good must be fleet members (known senders), in
        ascending order, never the sender; pgone within gone and only beside prev (`gone_problem`)."""
        if not gone:
            raise _Reject("gone", "'pgone' without 'gone' (what a robot knows to be gone only grows)")
        if pgone and not has_prev:
            raise _Reject("gone", "'pgone' without 'prev'")
        unknown = [j for j in (*gone, *pgone) if j not in self.known_senders]
        if unknown:
            raise _Reject("gone", f"'gone' names robot(s) {unknown[:8]} outside the fleet")
        why = gone_problem(sender, gone, pgone)
        if why is not None:
            raise _Reject("gone", why.replace("prev_gone", "pgone"))

    @classmethod
    def _unpack(cls, data: bytes | bytearray | memoryview) -> dict[str, Any]:
        obj = cls._unpack_object(data)
        if not isinstance(obj, list):  # arrays are tuples (use_list=False), maps are lists
            raise _Reject("not-a-map", f"top-level {type(obj).__name__}, not a map")
        frame: dict[str, Any] = dict(obj)
        if len(frame) != len(obj):  # a key appeared twice: name the first repeated one
            seen: set[Any] = set()
            for key, _value in obj:
                if key in seen:
                    raise _Reject("duplicate-field", f"field {key!r} appears twice")
                seen.add(key)
        return frame

    @staticmethod
    def _unpack_object(data: bytes | bytearray | memoryview) -> Any:
        try:
            # Limits bound memory per frame; maps come out as pair lists so duplicate keys show.
            # msgpack's exception set is not fully documented (ValueError, StackError,
            # UnicodeDecodeError, TypeError for unhashable keys...): any failure is "not-msgpack".
            obj = msgpack.unpackb(
                data,
                raw=False,
                use_list=False,
                strict_map_key=True,
                object_pairs_hook=list,
                max_str_len=1024,
                max_bin_len=MAX_FRAME_BYTES,
                max_array_len=1024,
                max_map_len=1024,
                max_ext_len=0,
            )
        except Exception as e:
            detail = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
            raise _Reject("not-msgpack", detail[:200]) from None
        return obj

    @staticmethod
    def _check_version_and_kind(frame: dict[str, Any]) -> None:
        for name, want, reason in (("v", FRAME_VERSION, "version"), ("kind", KIND_STATE, "kind")):
            if name not in frame:
                raise _Reject("missing-field", f"missing field(s) [{name!r}]")
            got = frame[name]
            if type(got) is not type(want):
                raise _Reject("field-type", f"{name!r} has type {type(got).__name__}")
            if got != want:
                raise _Reject(reason, f"{name!r} is {got!r:.80}, expected {want!r}")

    def _vector(self, name: str, raw: bytes) -> np.ndarray:
        """``raw`` as a read-only float64 vector (_read_only) if it is ``dim`` finite values."""
        if len(raw) != 8 * self.dim:
            raise _Reject(
                "vector-length", f"{name!r} has {len(raw)} bytes, expected {8 * self.dim}"
            )
        arr = _read_only(raw)
        if not _all_finite(arr):
            raise _Reject("non-finite", f"{name!r} holds NaN or inf")
        return arr
