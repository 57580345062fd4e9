"""Frame codec: exact wire format, exhaustive rejection, and properties over arbitrary input."""

import collections
import hashlib
import math
import re
import struct
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol.frames import (
    CONFIG_TAG_SIZE,
    FRAME_VERSION,
    MAX_DIM,
    MAX_FLAGS,
    MAX_FRAME_BYTES,
    MAX_ROUND,
    MAX_SEQ,
    REJECTION_REASONS,
    Decoded,
    FrameDecoder,
    Rejected,
    StateUpdate,
    config_tag,
    encode_state,
)

FLEET = "alpha"
TAG = config_tag("test-problem", 0.5, np.linspace(0.0, 1.0, 5))
OTHER_TAG = config_tag("test-problem", 0.25, np.linspace(0.0, 1.0, 5))
DIM = 4
KNOWN = (0, 1, 2, 7)
X = np.array([0.5, -1.25, 3.0e-300, 1.0e300])
PREV = np.array([-0.0, 2.0, 5e-324, -7.5])


def decoder() -> FrameDecoder:
    return FrameDecoder(FLEET, KNOWN, DIM, TAG)


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def le(values) -> bytes:
    return np.asarray(values, "<f8").tobytes()


def valid_map(**changes) -> dict:
    """A valid frame as a dict; ``changes`` replace fields, a value of ``...`` deletes one."""
    frame = {
        "v": FRAME_VERSION,
        "kind": "state",
        "fleet": FLEET,
        "from": 1,
        "round": 5,
        "seq": 42,
        "cfg": TAG,
        "x": le(X),
        "flags": 3,
        "prev": le(PREV),
        "pflags": 1,
    }
    for key, value in changes.items():
        if value is ...:
            del frame[key]
        else:
            frame[key] = value
    return frame


def raw_map(*pairs) -> bytes:
    """A msgpack map built pair by pair, so keys may repeat."""
    assert len(pairs) < 16
    return bytes([0x80 | len(pairs)]) + b"".join(pack(k) + pack(v) for k, v in pairs)


# ---------------------------------------------------------------------------------- wire format


def test_encoded_frame_is_the_documented_map():
    update = StateUpdate(sender=1, round=5, values=X, flags=3, prev_values=PREV, prev_flags=1)
    data = encode_state(update, fleet=FLEET, seq=42, config_tag=TAG)
    frame = msgpack.unpackb(data, raw=False)
    assert frame == valid_map()
    assert list(frame) == ["v", "kind", "fleet", "from", "round", "seq", "cfg", "x", "flags",
                           "prev", "pflags"]
    # vectors are single bin objects of little-endian float64, not arrays of floats
    assert data.count(b"\xc4\x20") == 2  # bin8 header, 32 bytes each
    assert np.frombuffer(frame["x"], "<f8").tolist() == X.tolist()


def test_need_is_optional_and_round_trips():
    """The optional "need" field: left out when not given, sorted when given, decoded as a
    tuple (None when absent); a frame with it carries the same update as one without."""
    update = StateUpdate(sender=1, round=5, values=X, flags=3, prev_values=PREV, prev_flags=1)
    plain = decoder().decode(encode_state(update, fleet=FLEET, seq=42, config_tag=TAG))
    data = encode_state(update, fleet=FLEET, seq=42, config_tag=TAG, need=[2, 0])
    assert msgpack.unpackb(data, raw=False)["need"] == [0, 2]
    got = decoder().decode(data)
    assert isinstance(got, Decoded) and got.need == (0, 2) and got.update == plain.update
    assert plain.need is None
    assert decoder().decode(encode_state(update, fleet=FLEET, seq=42, config_tag=TAG, need=())).need == ()


def test_golden_frame_bytes():
    """The example in docs/protocol.md, byte for byte: the format must not drift silently."""
    update = StateUpdate(sender=3, round=12, values=[0.25, -1.0], flags=1,
                         prev_values=[0.5, -0.75], prev_flags=0)
    data = encode_state(update, fleet="demo", seq=57,
                        config_tag=bytes.fromhex("0123456789abcdef"))
    doc = (Path(__file__).parents[1] / "docs" / "protocol.md").read_text()
    example = re.search(r"116 bytes:\n\n```\n(.*?)```", doc, re.S).group(1)
    assert data == bytes.fromhex(example.replace("\n", " "))


def test_documented_rejection_codes_match():
    doc = (Path(__file__).parents[1] / "docs" / "protocol.md").read_text()
    section = doc.split("## Validation and rejection codes")[1].split("\n## ")[0]
    assert tuple(re.findall(r"^\| `([a-z-]+)` \|", section, re.M)) == REJECTION_REASONS


def test_round_zero_frame_has_nil_prev():
    update = StateUpdate(sender=0, round=0, values=X, flags=0, prev_values=None)
    frame = msgpack.unpackb(encode_state(update, fleet=FLEET, seq=0, config_tag=TAG))
    assert frame["prev"] is None and frame["pflags"] == 0


@pytest.mark.parametrize("dim", [1, 2, 3, 17, 101, 1000, 4096])
@pytest.mark.parametrize("with_prev", [False, True])
def test_round_trip_shapes(dim, with_prev):
    rng = np.random.default_rng(dim)
    values = rng.standard_normal(dim) * 10.0 ** rng.integers(-300, 300, dim)
    prev = rng.standard_normal(dim) if with_prev else None
    update = StateUpdate(sender=7, round=1 if with_prev else 0, values=values,
                         flags=MAX_FLAGS, prev_values=prev, prev_flags=5 if with_prev else 0)
    dec = FrameDecoder(FLEET, KNOWN, dim, TAG)
    result = dec.decode(encode_state(update, fleet=FLEET, seq=MAX_SEQ, config_tag=TAG))
    assert result == Decoded(update, MAX_SEQ)
    assert result.update.values.tobytes() == values.tobytes()
    assert dec.accepted == 1 and not dec.counts


def test_decode_accepts_bytearray_and_memoryview():
    data = pack(valid_map())
    for view in (bytearray(data), memoryview(data)):
        assert decoder().decode(view) == decoder().decode(data)
    big = np.zeros(MAX_FRAME_BYTES // 8 + 1)  # 8-byte items: size is counted in bytes
    assert decoder().decode(memoryview(big)).reason == "too-large"
    assert decoder().decode(memoryview(np.zeros(8))[::2]).reason == "not-msgpack"


def _try_to_overwrite(update: StateUpdate) -> None:
    """What a careless or hostile core could do to the arrays it was handed: write them, or make
    them writable first. Either raises (read-only, shared) or touches only its own copy."""
    for arr in (update.values, update.prev_values):
        try:
            arr[:] = 0.0
        except ValueError:
            pass
        try:
            arr.flags.writeable = True
            arr[:] = 99.0
        except ValueError:
            pass


def test_no_receiver_can_alter_the_values_another_receiver_gets():
    data = pack(valid_map())
    first, second = decoder().decode(data).update, decoder().decode(data).update
    assert first.values.dtype == np.float64 and first.prev_values.dtype == np.float64
    _try_to_overwrite(first)
    for update in (first, second, decoder().decode(data).update):
        assert update.values.tolist() == X.tolist() and update.prev_values.tolist() == PREV.tolist()
    # the shared arrays are read-only views of the frame's immutable bytes: writing raises
    with pytest.raises(ValueError):
        first.values[0] = 1.0
    with pytest.raises(ValueError):
        first.prev_values.flags.writeable = True



def _count_body_hashes(monkeypatch) -> list[bytes]:
    """Every body digest (protocol/auth.py body_digest) computed from now on, by frames or auth."""
    from protocol import auth as auth_mod, frames

    hashed: list[bytes] = []
    real = auth_mod.body_digest

    def counted(body: bytes) -> bytes:
        hashed.append(body)
        return real(body)

    monkeypatch.setattr(frames, "body_digest", counted)
    monkeypatch.setattr(auth_mod, "body_digest", counted)
    return hashed


def _clear_memo() -> None:
    """Forget every parsed frame: the state of another process."""
    from protocol import frames

    frames._MEMO._items.clear(), frames._MEMO._order.clear()
    frames._MEMO._bytes = 0


def test_a_frame_tagged_here_is_hashed_once_by_its_sender_and_checked_per_receiver(monkeypatch):
    """Hash-then-MAC: the sender hashes a body once for all its neighbours' tags and primes the
    process's memo with that digest, so the receivers of the process check their own tags (one
    keyed hash of 40 bytes each) without hashing the body again; a receiver holding another key
    for the edge rejects it. (The earlier shortcut -- a receiver with the tagging key skipping its
    tag check -- is gone: the check no longer hashes the body.) In another process the body is
    hashed once, by its first receiver, for all of them."""
    _clear_memo()
    hashed = _count_body_hashes(monkeypatch)
    update = StateUpdate(1, 31, X, 1, PREV)
    data = encode_state(update, fleet=FLEET, seq=78, config_tag=TAG, auth=auth(1), prime=auth_decoder(1))
    assert len(hashed) == 1
    for me in (0, 2):
        got = auth_decoder(me).decode(data, expected_sender=1)
        assert isinstance(got, Decoded) and got.update == update
    assert len(hashed) == 1
    keys = dict(auth(0).keys)
    keys[1] = bytes(32)  # robot 0 holding another key for the edge {0, 1} than robot 1 tagged with
    other = FrameDecoder(FLEET, KNOWN, DIM, TAG, auth=FrameAuth(0, keys)).decode(data, expected_sender=1)
    assert isinstance(other, Rejected) and other.reason == "auth" and len(hashed) == 1
    _clear_memo()  # another process: nothing tagged here
    for me in (0, 2):
        assert isinstance(auth_decoder(me).decode(data, expected_sender=1), Decoded)
    assert len(hashed) == 2 and hashed[0] == hashed[1] == envelope(data)[1]


def test_the_body_is_hashed_once_per_sent_frame_whatever_the_neighbours(monkeypatch):
    """A robot with 15 neighbours (16 robots, complete graph) hashes each frame body once, not once
    per neighbour; each of the 15 receivers, each in its own process, hashes the body once and
    accepts it; its tag is the documented hash-then-MAC of that body."""
    from protocol.auth import digest_tag

    others = range(1, 16)
    sender = FrameAuth.from_secret(SECRET, 0, others)
    hashed = _count_body_hashes(monkeypatch)
    update = StateUpdate(0, 3, X, 0, PREV)
    data = encode_state(update, fleet=FLEET, seq=5, config_tag=TAG, auth=sender)
    assert len(hashed) == 1
    body = envelope(data)[1]
    D = hashlib.blake2b(body, digest_size=32, person=b"shapefleet-body2").digest()
    for j in others:
        hashed.clear()
        _clear_memo()
        dec = FrameDecoder(FLEET, range(16), DIM, TAG, auth=FrameAuth.from_secret(SECRET, j, (k for k in range(16) if k != j)))
        assert isinstance(dec.decode(data, expected_sender=0), Decoded) and hashed == [body]
        want = hashlib.blake2b(struct.pack("<II", 0, j) + D, key=edge_key(SECRET, 0, j), digest_size=16,
                               person=b"shapefleet-tag2").digest()
        assert envelope(data)[2][20 * (j - 1):20 * j] == struct.pack("<I", j) + want == (
            struct.pack("<I", j) + digest_tag(edge_key(SECRET, 0, j), 0, j, D))


def test_the_kept_packer_and_vector_bytes_give_msgpack_and_numpy_bytes():
    """encode_state packs with a Packer kept per thread and takes a float64 vector's own bytes
    (branch sendpath): the bytes of msgpack.packb and of np.asarray(v, "<f8").tobytes(), also
    right after a pack that failed, and for strided, float32, int and big-endian vectors."""
    from protocol.frames import _pack, _vector_bytes

    objs = [valid_map(), valid_map(need=[0, 2]), [1, pack(valid_map()), b"t" * 40], {"a": [1.5, None, True]}]
    for obj in objs:
        assert _pack(obj) == pack(obj)
        with pytest.raises(TypeError):
            _pack({"x": object()})
        assert _pack(obj) == pack(obj)
    base = np.arange(12, dtype=float) * 0.37 - 2.0
    for v in (base, base[::3], base[::-1], base.astype(np.float32), np.arange(5), base.astype(">f8"),
              np.array(base, order="F")):
        assert _vector_bytes("values", v) == np.asarray(v, "<f8").tobytes()

def test_encode_accepts_lists_and_float32_and_big_endian():
    for values in ([1, 2, 3, 4], np.float32([1, 2, 3, 4]), np.array([1, 2, 3, 4], ">f8")):
        update = StateUpdate(sender=0, round=0, values=values, flags=0, prev_values=None)
        out = decoder().decode(encode_state(update, fleet=FLEET, seq=0, config_tag=TAG))
        assert out.update.values.tolist() == [1.0, 2.0, 3.0, 4.0]


def test_largest_frame_fits_the_cap():
    update = StateUpdate(sender=MAX_FLAGS % 2**31, round=MAX_ROUND, values=np.ones(MAX_DIM),
                         flags=MAX_FLAGS, prev_values=np.ones(MAX_DIM), prev_flags=MAX_FLAGS)
    data = encode_state(update, fleet="f" * 64, seq=MAX_SEQ, config_tag=TAG)
    assert len(data) <= MAX_FRAME_BYTES


# ------------------------------------------------------------------------------------ rejection

NOT_MSGPACK_CASES = {
    "reserved-byte": b"\xc1",
    "empty": b"",
    "truncated": pack(valid_map())[:-1],
    "trailing-data": pack(valid_map()) + b"\xc0",
    "deep-nesting": b"\x91" * 5000 + b"\xc0",
    "ext-type": pack(msgpack.ExtType(5, b"abc")),
    "timestamp-ext": pack(msgpack.Timestamp(1, 0)),
    "bad-utf8": b"\xa2\xff\xfe",
    "int-map-key": pack({1: 2}),
    "nil-map-key": b"\x81\xc0\x01",
    "huge-array-header": b"\xdd\xff\xff\xff\xff",
    "huge-bin-header": b"\xc6\xff\xff\xff\xff",
    "str-input": "not bytes",
    "none-input": None,
}

REJECTION_CASES: dict[str, tuple[str, object]] = {
    **{f"too-large/{n}": ("too-large", b"\x00" * n) for n in (MAX_FRAME_BYTES + 1, 3 << 20)},
    **{f"not-msgpack/{k}": ("not-msgpack", v) for k, v in NOT_MSGPACK_CASES.items()},
    "not-a-map/int": ("not-a-map", pack(5)),
    "not-a-map/nil": ("not-a-map", pack(None)),
    "not-a-map/array": ("not-a-map", pack([1, 2])),
    "not-a-map/pairs": ("not-a-map", pack(list(valid_map().items()))),
    "not-a-map/bin": ("not-a-map", pack(pack(valid_map()))),
    "duplicate-field/v": ("duplicate-field", raw_map(*valid_map().items(), ("v", 1))),
    "duplicate-field/x": ("duplicate-field", raw_map(("x", le(X)), *valid_map().items())),
    "version/2": ("version", pack(valid_map(v=2))),
    "version/0": ("version", pack(valid_map(v=0))),
    "version/first": ("version", pack(valid_map(v=2, kind="?", extra=1, x=...))),
    "kind/status": ("kind", pack(valid_map(kind="status"))),
    "kind/empty": ("kind", pack(valid_map(kind=""))),
    "unknown-field/str": ("unknown-field", pack(valid_map(extra=1))),
    "unknown-field/bin-key": ("unknown-field", pack({**valid_map(), b"x": le(X)})),
    "fleet/other": ("fleet", pack(valid_map(fleet="beta"))),
    "fleet/case": ("fleet", pack(valid_map(fleet="Alpha"))),
    "config/other": ("config", pack(valid_map(cfg=OTHER_TAG))),
    "config/short": ("config", pack(valid_map(cfg=TAG[:7]))),
    "config/empty": ("config", pack(valid_map(cfg=b""))),
    "sender/unknown": ("sender", pack(valid_map(**{"from": 3}))),
    "sender/negative": ("sender", pack(valid_map(**{"from": -1}))),
    "sender/huge": ("sender", pack(valid_map(**{"from": 2**64 - 1}))),
    "round/negative": ("round", pack(valid_map(round=-1))),
    "round/too-big": ("round", pack(valid_map(round=MAX_ROUND + 1))),
    "seq/negative": ("seq", pack(valid_map(seq=-1))),
    "seq/too-big": ("seq", pack(valid_map(seq=MAX_SEQ + 1))),
    "flags/negative": ("flags", pack(valid_map(flags=-1))),
    "flags/too-big": ("flags", pack(valid_map(flags=MAX_FLAGS + 1))),
    "flags/pflags": ("flags", pack(valid_map(pflags=2**64 - 1))),
    "prev/at-round-0": ("prev", pack(valid_map(round=0))),
    "prev/pflags-without-prev": ("prev", pack(valid_map(prev=None))),
    "vector-length/x-short": ("vector-length", pack(valid_map(x=le(X[:3])))),
    "vector-length/x-long": ("vector-length", pack(valid_map(x=le(np.ones(5))))),
    "vector-length/x-odd": ("vector-length", pack(valid_map(x=le(X) + b"\x00"))),
    "vector-length/x-empty": ("vector-length", pack(valid_map(x=b""))),
    "vector-length/prev": ("vector-length", pack(valid_map(prev=le(PREV[:2])))),
    "need/unknown": ("need", pack(valid_map(need=[0, 3]))),
    "need/unsorted": ("need", pack(valid_map(need=[2, 0]))),
    "need/twice": ("need", pack(valid_map(need=[0, 0]))),
    "field-type/need/int": ("field-type", pack(valid_map(need=2))),
    "field-type/need/bool": ("field-type", pack(valid_map(need=[True]))),
    "field-type/need/nil-item": ("field-type", pack(valid_map(need=[None]))),
    # the robots dropped for good (agents/rounds.py floods them): fleet members, never the sender, sorted
    "gone/unknown": ("gone", pack(valid_map(gone=[0, 3]))),
    "gone/sender": ("gone", pack(valid_map(gone=[1]))),
    "gone/unsorted": ("gone", pack(valid_map(gone=[2, 0]))),
    "gone/twice": ("gone", pack(valid_map(gone=[0, 0]))),
    "gone/pgone-not-within-gone": ("gone", pack(valid_map(gone=[0], pgone=[2]))),
    "gone/pgone-without-gone": ("gone", pack(valid_map(pgone=[0]))),
    "gone/pgone-without-prev": ("gone", pack(valid_map(gone=[0], pgone=[0], prev=None, pflags=0))),
    "field-type/gone/int": ("field-type", pack(valid_map(gone=2))),
    "field-type/gone/bool": ("field-type", pack(valid_map(gone=[True]))),
    "field-type/pgone/nil-item": ("field-type", pack(valid_map(gone=[0], pgone=[None]))),
}
for _name in ("v", "kind", "fleet", "from", "round", "seq", "cfg", "x", "flags", "prev",
              "pflags"):
    REJECTION_CASES[f"missing-field/{_name}"] = ("missing-field", pack(valid_map(**{_name: ...})))
for _bad in (math.nan, math.inf, -math.inf):
    for _pos in (0, DIM - 1):
        for _field, _base in (("x", X), ("prev", PREV)):
            _vec = _base.copy()
            _vec[_pos] = _bad
            REJECTION_CASES[f"non-finite/{_field}[{_pos}]={_bad}"] = (
                "non-finite", pack(valid_map(**{_field: le(_vec)}))
            )
_WRONG_TYPES = {
    "v": [True, 1.0, "1", None],
    "kind": [b"state", None, 1],
    "fleet": [FLEET.encode(), 1, None, [FLEET]],
    "from": [True, False, 1.0, "1", None],
    "round": [True, 5.0, "5", None, [5]],
    "seq": [False, 42.0, b"\x2a", None],
    "cfg": [TAG.hex(), None, list(TAG)],
    "x": [X.tolist(), le(X).decode("latin-1"), None, {"data": le(X)}],
    "flags": [True, 3.0, None],
    "prev": [PREV.tolist(), 0, False, le(PREV).decode("latin-1")],
    "pflags": [True, 1.0, None],
}
for _name, _values in _WRONG_TYPES.items():
    for _i, _value in enumerate(_values):
        REJECTION_CASES[f"field-type/{_name}/{_i}"] = (
            "field-type", pack(valid_map(**{_name: _value}))
        )


AUTH_ONLY_REASONS = {"auth", "equivocation"}  # reachable with FrameDecoder(auth=...): tests below


def test_every_rejection_reason_is_reachable():
    assert {reason for reason, _ in REJECTION_CASES.values()} == set(REJECTION_REASONS) - AUTH_ONLY_REASONS
    # "auth" by the single frames of AUTH_CASES; "equivocation" needs two frames (its own test)
    assert "auth" in {reason for reason, _ in AUTH_CASES.values()}


@pytest.mark.parametrize(("reason", "data"), list(REJECTION_CASES.values()),
                         ids=list(REJECTION_CASES))
def test_rejection(reason, data):
    dec = decoder()
    result = dec.decode(data)
    assert isinstance(result, Rejected)
    assert (result.reason, dec.counts, dec.accepted) == (reason, {reason: 1}, 0)
    assert result.detail and len(result.detail) < 400


def test_expected_sender_must_match():
    dec = decoder()
    data = pack(valid_map())
    assert isinstance(dec.decode(data, expected_sender=1), Decoded)
    assert dec.decode(data, expected_sender=2) == Rejected("sender", "sender 1 on robot 2's key")
    assert dec.decode(data, expected_sender=None).seq == 42


def test_counters_accumulate():
    dec = decoder()
    expected = collections.Counter()
    for reason, data in REJECTION_CASES.values():
        dec.decode(data)
        expected[reason] += 1
    for _ in range(3):
        dec.decode(pack(valid_map()))
    assert dec.counts == expected and dec.accepted == 3


def test_version_is_checked_before_unknown_fields():
    """A future version may add fields; the receiver should say 'version', not 'unknown-field'."""
    result = decoder().decode(pack({"v": 2, "kind": "state", "x2": b""}))
    assert result.reason == "version"


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(fleet="a/b", known_senders=KNOWN, dim=DIM, config_tag=TAG),
        dict(fleet=FLEET, known_senders=[-1], dim=DIM, config_tag=TAG),
        dict(fleet=FLEET, known_senders=[True], dim=DIM, config_tag=TAG),
        dict(fleet=FLEET, known_senders=KNOWN, dim=0, config_tag=TAG),
        dict(fleet=FLEET, known_senders=KNOWN, dim=MAX_DIM + 1, config_tag=TAG),
        dict(fleet=FLEET, known_senders=KNOWN, dim=4.0, config_tag=TAG),
        dict(fleet=FLEET, known_senders=KNOWN, dim=DIM, config_tag=TAG[:4]),
        dict(fleet=FLEET, known_senders=KNOWN, dim=DIM, config_tag=TAG.hex()),
    ],
)
def test_decoder_rejects_bad_configuration(kwargs):
    with pytest.raises(ValueError):
        FrameDecoder(**kwargs)


# ---------------------------------------------------------------------- StateUpdate and encode


def test_state_update_equality():
    a = StateUpdate(sender=1, round=2, values=X, flags=0, prev_values=PREV)
    assert a == StateUpdate(sender=1, round=2, values=X.copy(), flags=0, prev_values=PREV.copy())
    assert a != StateUpdate(sender=1, round=2, values=X, flags=0, prev_values=None)
    assert a != StateUpdate(sender=1, round=2, values=X, flags=0, prev_values=PREV + 1)
    assert a != StateUpdate(sender=1, round=2, values=X, flags=1, prev_values=PREV)
    assert a != StateUpdate(sender=1, round=2, values=X[:3], flags=0, prev_values=PREV[:3])
    assert a != "not an update"
    with pytest.raises(TypeError):
        hash(a)


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        (dict(sender=True), ValueError),
        (dict(sender=-1), ValueError),
        (dict(round=-1), ValueError),
        (dict(round=MAX_ROUND + 1), ValueError),
        (dict(round=1.0), TypeError),
        (dict(flags=-1), ValueError),
        (dict(flags=MAX_FLAGS + 1), ValueError),
        (dict(flags=np.int64(1)), TypeError),
        (dict(prev_flags=1, prev_values=None), ValueError),
        (dict(round=0), ValueError),  # prev at round 0
        (dict(values=np.ones((2, 2)), prev_values=None), ValueError),
        (dict(values=np.ones(0), prev_values=None), ValueError),
        (dict(values=np.ones(4, complex), prev_values=None), TypeError),
        (dict(values=["a", "b"], prev_values=None), TypeError),
        (dict(prev_values=np.ones(3)), ValueError),
    ],
)
def test_state_update_validation(kwargs, error):
    base = dict(sender=1, round=2, values=X, flags=0, prev_values=PREV, prev_flags=0)
    with pytest.raises(error):
        StateUpdate(**{**base, **kwargs})


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(fleet="bad fleet"), "fleet id"),
        (dict(seq=-1), "seq"),
        (dict(seq=MAX_SEQ + 1), "seq"),
        (dict(config_tag=b"short"), "config_tag"),
        (dict(config_tag="0123456789abcdef"), "config_tag"),
    ],
)
def test_encode_validates_arguments(kwargs, match):
    update = StateUpdate(sender=1, round=2, values=X, flags=0, prev_values=PREV)
    with pytest.raises(ValueError, match=match):
        encode_state(update, **{**dict(fleet=FLEET, seq=0, config_tag=TAG), **kwargs})


@pytest.mark.parametrize("field", ["values", "prev_values"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_encode_refuses_non_finite(field, bad):
    kwargs = dict(sender=1, round=2, values=X.copy(), flags=0, prev_values=PREV.copy())
    kwargs[field][1] = bad
    with pytest.raises(ValueError, match="non-finite"):
        encode_state(StateUpdate(**kwargs), fleet=FLEET, seq=0, config_tag=TAG)


def test_encode_refuses_oversized_vector():
    update = StateUpdate(sender=1, round=0, values=np.ones(MAX_DIM + 1), flags=0,
                         prev_values=None)
    with pytest.raises(ValueError, match="MAX_DIM"):
        encode_state(update, fleet=FLEET, seq=0, config_tag=TAG)


# ----------------------------------------------------------------------------------- config_tag


def test_config_tag_is_stable():
    """Pinned: a change of the canonical serialisation would split mixed-version fleets."""
    tag = config_tag("rbf", 0.5, 2, np.array([[0.0, 1.0], [2.0, 3.5]]), [1, "a", None, True],
                     b"\x00\xff")
    assert len(tag) == CONFIG_TAG_SIZE
    assert tag.hex() == "62bce63c5aa0a2b1"


def test_config_tag_serialisation_matches_the_spec():
    """The byte layout documented in docs/protocol.md, rebuilt independently."""

    def q(n: int) -> bytes:
        return struct.pack("<Q", n)

    grid = np.array([[0.0, 1.0], [2.0, 3.5]])
    body = (
        b"L" + q(5)
        + b"S" + q(3) + b"rbf"
        + b"F" + struct.pack("<d", 0.5)
        + b"I" + q(2) + b"-2"
        + b"A" + q(2) + q(2) + q(2) + grid.astype("<f8").tobytes()
        + b"L" + q(4) + b"N" + b"B1" + b"Y" + q(2) + b"\x00\xff" + b"I" + q(1) + b"3"
    )
    expected = hashlib.blake2b(body, digest_size=8, person=b"shapefleet-cfg1").digest()
    assert config_tag("rbf", 0.5, -2, grid, (None, True, b"\x00\xff", 3.0)) == expected


def test_config_tag_equivalences_and_distinctions():
    grid = np.arange(6.0).reshape(2, 3)
    assert config_tag(2) == config_tag(2.0) == config_tag(np.int64(2)) == config_tag(np.float32(2))
    assert config_tag(0.0) == config_tag(-0.0)
    assert config_tag(grid) == config_tag(grid.astype(np.int32)) == config_tag(grid.T.T.copy())
    assert config_tag(np.array([-0.0, 1.0])) == config_tag(np.array([0.0, 1.0]))
    assert config_tag(grid) == config_tag(np.asfortranarray(grid))
    distinct = [
        config_tag(),
        config_tag(None),
        config_tag(True),
        config_tag(1),
        config_tag("1"),
        config_tag(b"1"),
        config_tag([1]),
        config_tag(np.array([1.0])),
        config_tag(np.array(1.0)),
        config_tag(grid),
        config_tag(grid.T),
        config_tag(grid.reshape(6)),
        config_tag("ab", "c"),
        config_tag("a", "bc"),
        config_tag(["a", "b"], "c"),
        config_tag(0.1),
        config_tag(np.float32(0.1)),
        config_tag(math.inf),
        config_tag(-math.inf),
        config_tag(2**70),
    ]
    assert len(set(distinct)) == len(distinct)


@pytest.mark.parametrize(
    ("part", "error"),
    [
        (math.nan, ValueError),
        (np.array([1.0, math.nan]), ValueError),
        ({"a": 1}, TypeError),
        (1 + 2j, TypeError),
        (np.array(["a"]), TypeError),
        (object(), TypeError),
    ],
)
def test_config_tag_refuses_what_it_cannot_fingerprint(part, error):
    with pytest.raises(error):
        config_tag(part)


# ----------------------------------------------------------------------------------- properties

finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def updates(draw, dim=None):
    dim = dim or draw(st.integers(1, 40))
    vec = st.lists(finite, min_size=dim, max_size=dim).map(np.array)
    rnd = draw(st.integers(0, MAX_ROUND))
    prev = draw(vec) if rnd > 0 and draw(st.booleans()) else None
    return StateUpdate(
        sender=draw(st.sampled_from(KNOWN)),
        round=rnd,
        values=draw(vec),
        flags=draw(st.integers(0, MAX_FLAGS)),
        prev_values=prev,
        prev_flags=draw(st.integers(0, MAX_FLAGS)) if prev is not None else 0,
    )


@given(updates(), st.integers(0, MAX_SEQ))
def test_valid_frames_round_trip_bit_for_bit(update, seq):
    dec = FrameDecoder(FLEET, KNOWN, update.values.size, TAG)
    result = dec.decode(encode_state(update, fleet=FLEET, seq=seq, config_tag=TAG))
    assert isinstance(result, Decoded) and result.seq == seq
    assert result.update == update
    assert result.update.values.tobytes() == update.values.tobytes()  # -0.0, subnormals
    if update.prev_values is not None:
        assert result.update.prev_values.tobytes() == update.prev_values.tobytes()


def _check_total(data) -> None:
    dec = decoder()
    result = dec.decode(data)
    assert isinstance(result, (Decoded, Rejected))
    if isinstance(result, Rejected):
        assert result.reason in REJECTION_REASONS and dec.counts == {result.reason: 1}
    else:
        assert dec.accepted == 1


@given(st.binary(max_size=512))
def test_decode_never_raises_on_bytes(data):
    _check_total(data)


msgpack_leaves = (
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
    | st.text(max_size=20) | st.binary(max_size=40)
)
msgpack_values = st.recursive(
    msgpack_leaves,
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=8) | st.binary(max_size=4), children, max_size=4),
    max_leaves=6,
)
field_names = st.sampled_from(sorted(valid_map())) | st.text(max_size=6)


@given(st.dictionaries(field_names, msgpack_leaves | st.lists(msgpack_leaves, max_size=3),
                       max_size=12))
def test_decode_never_raises_on_arbitrary_maps(frame):
    _check_total(pack(frame))


@given(msgpack_values)
def test_decode_never_raises_on_arbitrary_values(value):
    _check_total(pack(value))


@given(st.dictionaries(field_names, msgpack_values | st.none(), max_size=4))
def test_decode_never_raises_on_near_valid_frames(changes):
    """Mostly-valid frames reach the deep checks that random maps rarely get to."""
    frame = valid_map()
    frame.update(changes)
    _check_total(pack(frame))


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_decode_never_raises_on_mutated_frames(data):
    frame = bytearray(pack(valid_map()))
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(frame) - 1))
        frame[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(frame)))
    _check_total(bytes(frame[:cut]))


# ------------------------------------------------------------------------------ authentication

from protocol.auth import TAG_BYTES, FrameAuth, edge_key, new_fleet_secret  # noqa: E402

SECRET = bytes(range(32))
OTHER_SECRET = bytes(range(1, 33))
# robot 1's neighbours are 0 and 2; 0 and 2 are also neighbours (a triangle); 7 is a stranger
NEIGHBOURS = {0: (1, 2), 1: (0, 2), 2: (0, 1), 7: ()}


def auth(me: int, secret: bytes = SECRET) -> FrameAuth:
    return FrameAuth.from_secret(secret, me, NEIGHBOURS[me])


def auth_decoder(me: int = 0, secret: bytes = SECRET) -> FrameDecoder:
    return FrameDecoder(FLEET, KNOWN, DIM, TAG, auth=auth(me, secret))


def signed(update: StateUpdate | None = None, *, seq: int = 42, signer: FrameAuth | None = None) -> bytes:
    update = update or StateUpdate(1, 12, X, 1, PREV)
    return encode_state(update, fleet=FLEET, seq=seq, config_tag=TAG, auth=signer or auth(update.sender))


def envelope(data: bytes) -> tuple[int, bytes, bytes]:
    sender, body, tags = msgpack.unpackb(data, raw=False)
    return sender, body, tags


def rewrap(sender: int, body: bytes, tags: bytes) -> bytes:
    return pack([sender, body, tags])


def _forged_tag() -> bytes:
    sender, body, tags = envelope(signed())
    return rewrap(sender, body, tags[:4] + bytes(TAG_BYTES) + tags[4 + TAG_BYTES:])


def _tag_from_another_robots_key() -> bytes:
    # robot 2 signs a frame that claims to be robot 1's: its keys are not robot 1's edge keys
    body = encode_state(StateUpdate(1, 12, X, 1, PREV), fleet=FLEET, seq=42, config_tag=TAG)
    tags = b"".join(struct.pack("<I", j) + t for j, t in auth(2).tags(body).items())
    return rewrap(1, body, tags)


def _tampered_byte() -> bytes:
    sender, body, tags = envelope(signed())
    i = body.index(le(X)) + 3  # a byte inside x: the frame stays valid msgpack
    return rewrap(sender, body[:i] + bytes([body[i] ^ 0x01]) + body[i + 1:], tags)


def _replayed_as_another_round() -> bytes:
    sender, body, tags = envelope(signed())
    frame = msgpack.unpackb(body, raw=False)
    frame["round"] = 13
    return rewrap(sender, pack(frame), tags)


def _other_fleet_same_id() -> bytes:
    return signed(signer=auth(1, OTHER_SECRET))


def _old_scheme_tag() -> bytes:
    # the scheme before hash-then-MAC: a keyed hash of the whole body, person "shapefleet-tag1"
    sender, body, _ = envelope(signed())
    tag = hashlib.blake2b(struct.pack("<II", 1, 0) + body, key=edge_key(SECRET, 0, 1), digest_size=16,
                          person=b"shapefleet-tag1").digest()
    return rewrap(sender, body, struct.pack("<I", 0) + tag)


def _body_changed_after_tagging() -> bytes:
    # the tags of a genuine frame around another body of robot 1 (other x, same round and seq)
    sender, _, tags = envelope(signed())
    other = encode_state(StateUpdate(1, 12, X * 2, 1, PREV), fleet=FLEET, seq=42, config_tag=TAG)
    return rewrap(sender, other, tags)


def _tag_moved_from_another_edge() -> bytes:
    # robot 1's genuine tag for robot 2, filed under robot 0
    sender, body, tags = envelope(signed())
    return rewrap(sender, body, struct.pack("<I", 0) + auth(1).tags(body)[2])


def _tag_reflected() -> bytes:
    # the tag of this very body on the edge {0, 1} but in the other direction (0 -> 1): what robot 0
    # would send robot 1, handed back to robot 0 as robot 1's
    from protocol.auth import frame_tag

    sender, body, _ = envelope(signed())
    return rewrap(sender, body, struct.pack("<I", 0) + frame_tag(edge_key(SECRET, 0, 1), 0, 1, body))


AUTH_CASES = {
    "old-scheme-tag": ("auth", _old_scheme_tag()),
    "body-changed-after-tagging": ("auth", _body_changed_after_tagging()),
    "tag-moved-from-another-edge": ("auth", _tag_moved_from_another_edge()),
    "tag-reflected": ("auth", _tag_reflected()),
    "unauthenticated": ("auth", pack(valid_map())),
    "forged-tag": ("auth", _forged_tag()),
    "another-robots-key": ("auth", _tag_from_another_robots_key()),
    "tampered-byte": ("auth", _tampered_byte()),
    "replayed-as-round-13": ("auth", _replayed_as_another_round()),
    "other-fleet-secret": ("auth", _other_fleet_same_id()),
    "no-tag-for-me": ("auth", signed(signer=FrameAuth(1, {2: edge_key(SECRET, 1, 2)}))),
    "malformed-envelope": ("auth", pack([1, b"x"])),
    "stranger": ("sender", pack([9, pack(valid_map()), b""])),
}


@pytest.mark.parametrize(("reason", "data"), list(AUTH_CASES.values()), ids=list(AUTH_CASES))
def test_auth_rejection(reason, data):
    dec = auth_decoder(0)
    result = dec.decode(data, expected_sender=None if reason == "sender" else 1)
    assert isinstance(result, Rejected), result
    assert (result.reason, dec.counts, dec.accepted) == (reason, {reason: 1}, 0)
    # the genuine frame still passes afterwards: a forgery does not poison the decoder
    assert isinstance(dec.decode(signed(), expected_sender=1), Decoded)


def test_signed_frame_is_accepted_by_each_neighbour_and_only_them():
    data = signed()
    for me in (0, 2):
        dec = auth_decoder(me)
        result = dec.decode(data, expected_sender=1)
        assert isinstance(result, Decoded) and result.update == StateUpdate(1, 12, X, 1, PREV)
    stranger = FrameDecoder(FLEET, KNOWN, DIM, TAG, auth=auth(7))
    assert stranger.decode(data, expected_sender=1).reason == "auth"  # shares no key with robot 1
    # robot 0 holds k_01 and could forge "robot 1" towards itself, but not towards robot 2:
    body = encode_state(StateUpdate(1, 12, 2 * X, 1, PREV), fleet=FLEET, seq=1, config_tag=TAG)
    k01 = auth(0).keys[1]
    from protocol.auth import frame_tag

    forged = rewrap(1, body, struct.pack("<I", 2) + frame_tag(k01, 1, 2, body))
    assert auth_decoder(2).decode(forged, expected_sender=1).reason == "auth"


def test_a_receiver_named_twice_in_the_tag_block_is_judged_by_its_first_tag():
    from protocol.auth import frame_tag

    sender, body, _ = envelope(signed(seq=9))
    good = frame_tag(edge_key(SECRET, 0, 1), 1, 0, body)
    bad = bytes(16)
    first_good = rewrap(1, body, struct.pack("<I", 0) + good + struct.pack("<I", 0) + bad)
    first_bad = rewrap(1, body, struct.pack("<I", 0) + bad + struct.pack("<I", 0) + good)
    assert isinstance(auth_decoder(0).decode(first_good, expected_sender=1), Decoded)
    assert auth_decoder(0).decode(first_bad, expected_sender=1).reason == "auth"


def test_signer_must_be_the_sender():
    with pytest.raises(ValueError, match="cannot sign"):
        encode_state(StateUpdate(2, 1, X, 0, None), fleet=FLEET, seq=0, config_tag=TAG, auth=auth(1))


def test_equivocation_is_rejected_and_the_first_frame_kept():
    dec = auth_decoder(0)
    first = StateUpdate(1, 12, X, 1, PREV)
    assert isinstance(dec.decode(signed(first, seq=1), expected_sender=1), Decoded)
    # retransmission (new seq, same values) and a later frame carrying round 12 as prev: fine
    assert isinstance(dec.decode(signed(first, seq=2), expected_sender=1), Decoded)
    nxt = StateUpdate(1, 13, 2 * X, 0, X, prev_flags=1)
    assert isinstance(dec.decode(signed(nxt, seq=3), expected_sender=1), Decoded)
    # a different x for round 12, a different flag for it, a different prev for round 12
    for bad in (
        StateUpdate(1, 12, X * 1.02, 1, PREV),
        StateUpdate(1, 12, X, 0, PREV),
        StateUpdate(1, 13, 2 * X, 0, X * 1.5, prev_flags=1),
        StateUpdate(1, 12, X, 1, PREV * 2),  # its prev (round 11) contradicts the first frame's
    ):
        result = dec.decode(signed(bad, seq=4), expected_sender=1)
        assert isinstance(result, Rejected) and result.reason == "equivocation", bad
    assert dec.counts == {"equivocation": 4} and dec.accepted == 3
    # the first frame is still the one that counts: resending it passes
    assert isinstance(dec.decode(signed(first, seq=5), expected_sender=1), Decoded)
    # another sender's round 12 is its own business
    assert isinstance(dec.decode(signed(StateUpdate(2, 12, -X, 0, None)), expected_sender=2), Decoded)


def test_equivocation_memory_is_bounded():
    from protocol.frames import EQUIVOCATION_WINDOW

    dec = auth_decoder(0)
    for rnd in range(1, 200):
        assert isinstance(dec.decode(signed(StateUpdate(1, rnd, X + rnd, 0, X + rnd - 1))), Decoded)
    assert len(dec._seen[1]) <= EQUIVOCATION_WINDOW


def test_fleet_secret_and_edge_keys():
    a, b = new_fleet_secret(), new_fleet_secret()
    assert len(a) == 32 and a != b
    assert edge_key(a, 1, 2) == edge_key(a, 2, 1) != edge_key(a, 1, 3)
    assert edge_key(a, 1, 2) != edge_key(b, 1, 2)
    with pytest.raises(ValueError):
        edge_key(a, 1, 1)
    with pytest.raises(ValueError):
        edge_key(a[:16], 1, 2)
    with pytest.raises(ValueError):
        FrameAuth(1, {2: b"short"})


@given(updates(), st.integers(0, MAX_SEQ))
def test_valid_signed_frames_round_trip_bit_for_bit(update, seq):
    me = next(j for j in KNOWN if j != update.sender)
    signer = FrameAuth.from_secret(SECRET, update.sender, [me])
    dec = FrameDecoder(FLEET, KNOWN, update.values.size, TAG, auth=FrameAuth.from_secret(SECRET, me, [update.sender]))
    result = dec.decode(encode_state(update, fleet=FLEET, seq=seq, config_tag=TAG, auth=signer),
                        expected_sender=update.sender)
    assert isinstance(result, Decoded) and result.seq == seq and result.update == update
    assert result.update.values.tobytes() == update.values.tobytes()


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_signed_frames_are_rejected_never_accepted(data):
    """Any change to an authenticated frame is refused (and the decoder never raises)."""
    original = signed()
    frame = bytearray(original)
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(frame) - 1))
        frame[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(frame)))
    mutated = bytes(frame[:cut])
    dec = auth_decoder(0)
    result = dec.decode(mutated, expected_sender=1)
    if mutated == original:
        assert isinstance(result, Decoded)
    else:
        # a change may leave the body and our tag intact (e.g. in the tag to robot 2): then the
        # frame is the genuine one; otherwise it is refused
        if isinstance(result, Decoded):
            assert result.update == StateUpdate(1, 12, X, 1, PREV)
        else:
            assert result.reason in REJECTION_REASONS and dec.counts == {result.reason: 1}


# ------------------------------------------------------------------------ keys in fleet files


def test_fleet_files_hold_the_secret_or_only_the_robots_own_edge_keys(tmp_path):
    import json

    from agents.spec import FleetSpec
    from tests.conftest import make_run

    _world, spec, _central = make_run(robots=4, topology="line", fleet_id="keys")  # 0-1-2-3
    assert spec.secret is not None and len(spec.secret) == 32
    assert make_run(fleet_id="keys")[1].secret != spec.secret  # a fresh secret per fleet
    spec.save(tmp_path / "full.json")
    assert json.loads((tmp_path / "full.json").read_text())["auth"] == {"secret": spec.secret.hex()}
    full_keys = {i: spec.frame_auth(i).keys for i in spec.robot_ids}
    assert set(full_keys[1]) == {0, 2} and full_keys[1][2] == full_keys[2][1] != full_keys[1][0]
    for i in spec.robot_ids:
        own = spec.for_robot(i)
        own.save(tmp_path / f"{i}.json")
        data = json.loads((tmp_path / f"{i}.json").read_text())
        assert "secret" not in data["auth"] and "secret" not in json.dumps(data)
        assert data["auth"]["edge_keys"] == {str(j): k.hex() for j, k in sorted(full_keys[i].items())}
        back = FleetSpec.load(tmp_path / f"{i}.json")
        assert back.secret is None and back.frame_auth(i).keys == full_keys[i]
        with pytest.raises(ValueError, match="frame keys only"):
            back.frame_auth((i + 1) % 4)
    # frames signed from a per-robot file verify with the neighbour's per-robot file
    one, two = FleetSpec.load(tmp_path / "1.json"), FleetSpec.load(tmp_path / "2.json")
    up = StateUpdate(1, 3, np.ones(spec.dim), 0, np.zeros(spec.dim))
    frame = encode_state(up, fleet=spec.fleet, seq=0, config_tag=spec.config_tag, auth=one.frame_auth(1))
    dec = FrameDecoder(spec.fleet, spec.robot_ids, spec.dim, spec.config_tag, auth=two.frame_auth(2))
    assert dec.decode(frame, expected_sender=1).update == up
    dec3 = FrameDecoder(spec.fleet, spec.robot_ids, spec.dim, spec.config_tag, auth=spec.frame_auth(3))
    assert dec3.decode(frame, expected_sender=1).reason == "auth"  # 3 is no neighbour of 1


def test_a_fleet_file_without_keys_is_refused_with_exit_2(tmp_path):
    import json
    import os
    import subprocess
    import sys

    from agents.spec import FleetSpec
    from tests.conftest import ROOT, make_run

    _world, spec, _central = make_run(fleet_id="old-file")
    data = spec.to_json()
    del data["auth"]
    old = tmp_path / "old.json"
    old.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"old\.json: not a valid fleet file \(no frame keys"):
        FleetSpec.load(old)
    proc = subprocess.run([sys.executable, "-m", "launcher.cli", "robot", "--fleet-file", str(old), "--id", "0",
                           "--connect", "tcp/127.0.0.1:9"], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "no frame keys" in lines[0] and "old.json" in lines[0], proc.stderr


# ------------------------------------------------------------------------------ parse memo


def test_parse_memo_is_shared_but_each_receiver_gets_its_own_verdict_and_cannot_alter_values():
    """Robots of one process parse a broadcast frame once (protocol.frames._MEMO); the tag check
    stays per receiver, and no receiver can change the values another one gets."""
    from protocol.frames import _MEMO

    data = signed(StateUpdate(1, 30, X, 1, PREV), seq=77)
    misses = _MEMO.misses
    first, second = auth_decoder(0).decode(data, expected_sender=1), auth_decoder(2).decode(data, expected_sender=1)
    assert _MEMO.misses - misses == 2  # the envelope and the body, once for both receivers
    assert isinstance(first, Decoded) and isinstance(second, Decoded)
    assert first.update == second.update == StateUpdate(1, 30, X, 1, PREV) and first.seq == 77
    _try_to_overwrite(first.update)  # a receiver writing what it got does not touch the other's
    assert second.update == StateUpdate(1, 30, X, 1, PREV)
    assert auth_decoder(2).decode(data, expected_sender=1).update.values[0] == X[0]
    # the memo holds the parse, not the authentication: a stranger still fails on the same bytes
    assert FrameDecoder(FLEET, KNOWN, DIM, TAG, auth=auth(7)).decode(data, expected_sender=1).reason == "auth"
    # a decoder that checks differently (another dimension) parses for itself and rejects
    assert FrameDecoder(FLEET, KNOWN, DIM + 1, TAG, auth=auth(0)).decode(data,
                                                                         expected_sender=1).reason == "vector-length"


_FOR_EVERY_RECEIVER = ("unauthenticated", "tampered-byte", "replayed-as-round-13", "malformed-envelope")


@pytest.mark.parametrize(("reason", "data"), [AUTH_CASES[k] for k in _FOR_EVERY_RECEIVER], ids=_FOR_EVERY_RECEIVER)
def test_a_memoised_rejection_is_the_same_for_every_receiver(reason, data):
    verdicts = [auth_decoder(me).decode(data, expected_sender=1) for me in (0, 2, 0)]
    assert all(isinstance(v, Rejected) and v.reason == reason for v in verdicts)
    assert verdicts[0].detail == verdicts[2].detail


def test_parse_memo_is_bounded_in_entries_and_bytes():
    from protocol.frames import _ParseMemo

    memo = _ParseMemo(max_entries=8, max_bytes=1000)
    for i in range(50):
        assert memo.get_or_parse(("k", bytes([i]) * 30), bytes([i]) * 30, len) == 30
    assert len(memo._items) == 8 and memo._bytes == 240
    for i in range(50):
        memo.get_or_parse(("k", bytes([i]) * 300), bytes([i]) * 300, len)
    assert len(memo._items) <= 3 and memo._bytes <= 1000
    # a bytearray is not hashable: parsed every time, never stored
    assert memo.get_or_parse(("k", None), bytearray(5), len) == 5 and memo._bytes <= 1000


def test_precomputed_edge_hashers_give_the_documented_tags():
    """FrameAuth copies a keyed hash state per edge (issue 14): its tags are still frame_tag's."""
    from protocol.auth import frame_tag

    body = b"any frame body"
    tags = auth(1).tags(body)
    assert tags == {j: frame_tag(edge_key(SECRET, 1, j), 1, j, body) for j in (0, 2)}
    assert auth(0).verify(1, body, tags[0]) and auth(2).verify(1, body, tags[2])
    assert not auth(0).verify(1, body, tags[2]) and not auth(0).verify(1, body + b"!", tags[0])
    assert auth(1).tags(body) == tags  # the precomputed states are copied, never consumed


def _reference_equivocation(seen: dict[int, tuple[int, bytes]], rnd: int, claim: tuple[int, bytes],
                            prev: tuple[int, bytes] | None) -> bool:
    """The window rule of docs/protocol.md ("Equivocation") written plainly: check, remember, then
    forget every round up to the newest - EQUIVOCATION_WINDOW. False: equivocation."""
    from protocol.frames import EQUIVOCATION_WINDOW

    if rnd in seen and seen[rnd] != claim:
        return False
    if prev is not None and rnd - 1 in seen and seen[rnd - 1] != prev:
        return False
    seen.setdefault(rnd, claim)
    if prev is not None:
        seen.setdefault(rnd - 1, prev)
    for r in [r for r in seen if r <= max(seen) - EQUIVOCATION_WINDOW]:
        del seen[r]
    return True


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, 30), st.integers(0, 1), st.integers(-1, 1)), min_size=1, max_size=40))
def test_equivocation_window_matches_the_plain_rule(frames_in):
    """The decoder's incremental window (pruned only when a sender's newest round moves) accepts and
    refuses exactly what the plain rule does, and remembers the same rounds, frame after frame:
    rounds jumping back and forth, values that differ (0/1), with or without prev (-1: none).
    Two receivers of the frames: the first parses each (decode's full path), the second takes
    decode's short path for a frame already parsed in the process (its own inline common case)."""
    _match_the_plain_rule(frames_in)


def test_equivocation_window_matches_the_plain_rule_over_a_long_honest_run():
    """The common case: a sender's rounds one after the other, each frame's prev the round
    before's values, for longer than the window -- then equivocations and late frames."""
    _match_the_plain_rule([(r, 0, 0) for r in range(20)] + [(11, 1, -1), (12, 0, 0), (20, 0, 1), (21, 0, 0)])


def _match_the_plain_rule(frames_in: list[tuple[int, int, int]]) -> None:
    first, dec = auth_decoder(2), auth_decoder(0)
    model: dict[int, tuple[int, bytes]] = {}
    for seq, (rnd, v, pv) in enumerate(frames_in):
        prev = None if pv < 0 or rnd == 0 else X + pv
        update = StateUpdate(1, rnd, X + v, 0, prev)
        data = signed(update, seq=seq)
        verdicts = [first.decode(data, expected_sender=1), dec.decode(data, expected_sender=1)]
        want = _reference_equivocation(model, rnd, (0, (X + v).tobytes()),
                                       None if prev is None else (0, prev.tobytes()))
        for got in verdicts:
            assert isinstance(got, Decoded) == want, (rnd, v, pv)
            if not want:
                assert got.reason == "equivocation"
        assert first._seen.get(1, {}) == model and dec._seen.get(1, {}) == model


def test_tag_entries_are_the_sorted_tags():
    """The envelope's tag block (built per sent frame without the dict) is each neighbour's tag of
    ``tags`` behind its id, by ascending id."""
    body = b"some frame body"
    a = FrameAuth.from_secret(SECRET, 1, (7, 0, 2))
    assert a.tag_entries(body) == b"".join(struct.pack("<I", j) + t for j, t in sorted(a.tags(body).items()))


def test_a_frame_another_receiver_accepted_is_still_checked_in_full_for_each():
    """Once a receiver of the process accepted a frame (envelope and body parsed, memoised), the
    next receivers take decode's short path only when everything holds for *them*; otherwise they
    get the full path's verdict: a wrong key (another fleet's secret), a frame on another robot's
    key, a receiver that is no neighbour of the sender, and equivocation against its own memory."""
    data = signed(StateUpdate(1, 40, X, 1, PREV), seq=5)
    assert isinstance(auth_decoder(0).decode(data, expected_sender=1), Decoded)  # memoised now
    assert auth_decoder(2, OTHER_SECRET).decode(data, expected_sender=1).reason == "auth"
    wrong_key = auth_decoder(2).decode(data, expected_sender=0)
    assert wrong_key.reason == "sender" and "robot 0's key" in wrong_key.detail
    assert FrameDecoder(FLEET, KNOWN, DIM, TAG, auth=auth(7)).decode(data, expected_sender=1).reason == "auth"
    dec = auth_decoder(2)
    assert isinstance(dec.decode(signed(StateUpdate(1, 40, -X, 1, PREV), seq=4), expected_sender=1), Decoded)
    again = dec.decode(data, expected_sender=1)  # round 40 with other values than it accepted
    assert again.reason == "equivocation" and dec.counts == {"equivocation": 1} and dec.accepted == 1
    assert isinstance(auth_decoder(2).decode(data, expected_sender=1), Decoded)  # a fresh receiver: fine


@pytest.mark.parametrize("authenticated", [True, False], ids=["authenticated", "unauthenticated"])
def test_a_primed_frame_decodes_exactly_as_its_parse_and_is_still_authenticated(authenticated):
    """encode_state(..., prime=decoder) (issue 14, branch shell3): the sender tells its process's
    parse memo what the frame's bytes parse to, so the robots of that process skip the parse; a
    receiver gets what parsing those bytes gives (fields, need, read-only arrays, bit for bit),
    its own tag is still checked, and other bytes are still parsed."""
    from protocol.frames import _MEMO

    def make(prime):
        kw = {"auth": auth(1)} if authenticated else {}
        return encode_state(StateUpdate(1, 31, X, 1, PREV), fleet=FLEET, seq=78, config_tag=TAG, need=(0, 2),
                            prime=prime, **kw)

    def receiver(me):
        return auth_decoder(me) if authenticated else FrameDecoder(FLEET, KNOWN, DIM, TAG)

    parsed = receiver(0).decode(make(None), expected_sender=1)  # the same bytes, parsed
    _MEMO._items.clear(), _MEMO._order.clear()
    _MEMO._bytes = 0
    data = make(receiver(1))
    misses = _MEMO.misses
    got = receiver(0).decode(data, expected_sender=1)
    assert _MEMO.misses == misses  # not parsed
    assert isinstance(got, Decoded) and isinstance(parsed, Decoded)
    assert (got.seq, got.need, got.update) == (parsed.seq, parsed.need, parsed.update) == (78, (0, 2),
                                                                                         StateUpdate(1, 31, X, 1, PREV))
    for a, b in ((got.update.values, parsed.update.values), (got.update.prev_values, parsed.update.prev_values)):
        assert a.tobytes() == b.tobytes() and not a.flags.writeable
    if authenticated:  # the memo holds the parse, not the authentication
        assert FrameDecoder(FLEET, KNOWN, DIM, TAG, auth=auth(0, OTHER_SECRET)).decode(
            data, expected_sender=1).reason == "auth"
    tampered = bytearray(data)
    tampered[data.index(np.asarray(X, "<f8").tobytes())] ^= 1  # the lowest bit of x[0]
    out = receiver(0).decode(bytes(tampered), expected_sender=1)
    assert _MEMO.misses > misses  # other bytes: parsed
    if authenticated:
        assert isinstance(out, Rejected) and out.reason == "auth"
    else:
        assert isinstance(out, Decoded) and out.update.values[0] != X[0] and out.update.values[1:].tobytes() == \
            np.asarray(X[1:], "<f8").tobytes()
