"""The wire protocol: every message round-trips, validation refuses what it must with the right
code, and the codec never fails with anything but ProtocolError (hypothesis)."""

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import (
    CLIENT_TYPES,
    SERVER_TYPES,
    AvatarInfo,
    AvatarReplaced,
    CameraSpec,
    Drive,
    Error,
    Frame,
    Hello,
    Image,
    Limits,
    Orbit,
    Ping,
    Pong,
    Presence,
    ProtocolError,
    Request,
    RoomWelcome,
    SeatPresence,
    Stats,
    Timings,
    Tracked,
    View,
    Voice,
    VoiceBounds,
    Welcome,
    decode_client,
    decode_server,
    encode,
    pack_array,
    unpack_array,
)
from protocol.messages import Answers
from protocol.params import FAMILIES, VALUE_KINDS

EYE = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
K = ((500.0, 0.0, 256.0), (0.0, 500.0, 256.0), (0.0, 0.0, 1.0))

CLIENT_EXAMPLES = [
    Hello(token="t" * 40, client="pytest"),
    Drive(seq=7, smplx={"jaw_pose": [0.1, 0, 0], "body_pose": np.zeros((21, 3), np.float32),
                        "expression": np.arange(10.0)},
          flame={"expr": np.ones(50), "eyes_pose": np.zeros(6)},
          mano_left={"hand_pose": np.zeros(45)}, mano_right={"hand_pose": np.zeros(6)},
          reset=True),
    View(orbit=Orbit(yaw_deg=30, pitch_deg=-10, distance=2.0, target=(0, 0.3, 0)),
         moving=True),
    View(camera=CameraSpec(K=K, R=EYE, t=(0, 0, 3), width=640, height=480)),
    Request(outputs=["rgb", "alpha", "depth"], width=320, height=240, background=(1, 1, 1),
            sh_degree=1, quality=0.5, jpeg_quality=70, codec="png", max_fps=24),
    Image(seq=3, format="png", data=b"\x89PNG fake but non-empty"),
    Ping(t=12.5),
    Hello(token="tsr_x", client="viewer", role="watch", seat=1),
    Hello(token="t", client="telesplat-web", name="Zoë O'Brien-2"),
    Voice(seq=4, data=b"\xf8\xff\xfe", t_capture=12.52),
    Image(seq=9, data=b"\xff\xd8 a camera frame", t_capture=33.25),  # minor 4
    Hello(token="t", client="viewer", role="watch", voice_mix=True),   # minor 4
    Drive(seq=8, flame={"jaw_pose": [0.2, 0, 0]}, t_capture=12.5),
]
SERVER_EXAMPLES = [
    Welcome(session="abc", avatar=AvatarInfo(id="demo", name="ada", num_gaussians=5,
                                             sh_degree=3, owner="public"),
            limits=Limits(), codecs=["jpeg", "png", "h264"], request=Request(width=512)),
    Frame(seq=7, frame=1, codec="jpeg", width=4, height=2, data=b"\xff\xd8",
          depth=b"png", keyframe=False, timings=Timings(track=1, pose=2, render=3, encode=4)),
    Frame(seq=8, frame=2, codec="jpeg", width=4, height=2, data=b"\xff\xd8", t_capture=12.5),
    Error(code="invalid", message="nope", answers=Answers(type="drive", seq=3)),
    Stats(fps=30, frames=10, dropped=1, coalesced=2, bytes_per_s=1e5, render_ms=12,
          sessions=1),
    Pong(t=1.0),
    Welcome(session="def", minor=1, avatar=AvatarInfo(id="demo", name="ada", num_gaussians=5,
                                                      sh_degree=3),
            limits=Limits(), codecs=["jpeg"], request=Request(width=512),
            room=RoomWelcome(id="r1", name="demo", role="perform", seat=0),
            voice=VoiceBounds(max_bitrate=128_000, max_packet_bytes=1276)),  # minor 4
    Presence(room="r1", seats=[SeatPresence(index=0, avatar="demo", performer="cam",
                                            holding=False)],
             viewers=3, event="join", who="viewer", role="watch"),
    Welcome(session="ghi", avatar=AvatarInfo(id="demo", name="ada", num_gaussians=5,
                                             sh_degree=3, expression_names=["smile", "frown"]),
            limits=Limits(), codecs=["jpeg"], request=Request(width=512)),
    Tracked(seq=4, found=True, seen={"face": True, "left_hand": False}),
    Tracked(seq=5, found=False),
    Voice(seq=4, data=b"\xf8\xff\xfe", t_capture=12.52, seat=0),
    AvatarReplaced(avatar=AvatarInfo(id="demo", name="ada", num_gaussians=9, sh_degree=3,
                                     owner="public", metadata={"trained": True}), seats=[0]),
]


def test_a_plain_welcome_carries_no_room_fields():
    """Old clients forbid unknown fields: room-only ones are left out of plain sessions."""
    plain = msgpack.unpackb(encode(SERVER_EXAMPLES[0]))
    assert "room" not in plain and "minor" not in plain
    assert "role" not in msgpack.unpackb(encode(Hello(token="t")))


def test_an_avatar_without_expression_names_sends_none():
    """Official body models name no expressions: the field is left out, not an empty list."""
    assert "expression_names" not in msgpack.unpackb(encode(SERVER_EXAMPLES[0]))["avatar"]


@pytest.mark.parametrize("name, shown", [
    ("  Ann   Lee ", "Ann Lee"), ("李雷", "李雷"), ("o'neil_2.b-c", "o'neil_2.b-c"),
    ("x" * 32, "x" * 32)])
def test_display_names_are_trimmed_and_kept(name, shown):
    back = decode_client(encode(Hello(name=name)))
    assert back.name == shown


@pytest.mark.parametrize("name, why", [
    ("", "must not be empty"), ("   ", "must not be empty"),
    ("x" * 33, "exceeds the limit 32"), ("<b>hi</b>", "letters, digits"),
    ("a\u202eb", "letters, digits"), ("tab\there", None), ("emoji \U0001f600", "letters")])
def test_display_names_are_bounded_and_plain(name, why):
    if why is None:  # whitespace of any kind collapses to one space
        assert decode_client(encode(Hello(name=name))).name == "tab here"
        return
    with pytest.raises(ProtocolError) as err:
        decode_client(msgpack.packb({"type": "hello", "name": name}))
    assert err.value.code == ("too_large" if "limit" in why else "invalid")
    assert why in err.value.message
    limits = Limits(max_name_chars=40)  # the limit is a setting
    if len(name) == 33:
        assert decode_client(msgpack.packb({"type": "hello", "name": name}), limits).name == name


def _same(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _same(a[k], b[k])
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b)
    else:
        assert a == b


@pytest.mark.parametrize("message", CLIENT_EXAMPLES, ids=lambda m: m.type)
def test_client_messages_round_trip(message):
    back = decode_client(encode(message))
    assert type(back) is type(message)
    _same(message.model_dump(), back.model_dump())


@pytest.mark.parametrize("message", SERVER_EXAMPLES, ids=lambda m: m.type)
def test_server_messages_round_trip(message):
    back = decode_server(encode(message))
    assert type(back) is type(message) and back == message


def test_every_message_type_has_an_example():
    assert {m.type for m in CLIENT_EXAMPLES} == set(CLIENT_TYPES)
    assert {m.type for m in SERVER_EXAMPLES} == set(SERVER_TYPES)


@pytest.mark.parametrize("dtype", ["<f4", "<f8", "<i4", "<i8", "|u1", "<u2"])
def test_arrays_pack_and_unpack_exactly(dtype):
    arr = (np.arange(24) - 5).astype(np.dtype(dtype)).reshape(2, 3, 4)
    packed = msgpack.unpackb(msgpack.packb(pack_array(arr), use_bin_type=True), raw=False)
    back = unpack_array(packed, max_elements=100)
    assert back.dtype == arr.dtype and back.shape == arr.shape
    np.testing.assert_array_equal(back, arr)
    big_endian = arr.astype(np.dtype(dtype).newbyteorder(">")) if arr.itemsize > 1 else arr
    np.testing.assert_array_equal(unpack_array(pack_array(big_endian), 100), arr)


def _raw(**fields):
    return msgpack.packb(fields, use_bin_type=True)


BAD_CLIENT = [
    (b"", "bad_message"),
    (b"\xc1", "bad_message"),                                     # reserved msgpack byte
    (msgpack.packb([1, 2, 3]), "bad_message"),                    # not a map
    (_raw(seq=1), "bad_message"),                                 # no type
    (_raw(type="frame", seq=1), "bad_message"),                   # a server type
    (_raw(type="drive"), "invalid"),                              # no seq
    (_raw(type="drive", seq=-1), "invalid"),
    (_raw(type="drive", seq=1, extra=True), "invalid"),           # unknown field
    (_raw(type="drive", seq=1, smplx={"jaw_pose": [0, 0]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"jaw_pose": [0, 0, math.nan]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"jaw_pose": [0, 0, math.inf]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"tail": [0, 0, 0]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"jaw_pose": "abc"}), "invalid"),
    (_raw(type="drive", seq=1, flame={"expr": list(range(101))}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"body_pose": {"nd": True, "dtype": "<f4",
                                                    "shape": [21, 3], "data": b"\0" * 4}}),
     "invalid"),                                                  # bytes do not fit the shape
    (_raw(type="drive", seq=1, smplx={"body_pose": {"nd": True, "dtype": "|O",
                                                    "shape": [1], "data": b"\0"}}), "invalid"),
    (_raw(type="view"), "invalid"),                               # neither orbit nor camera
    (_raw(type="view", orbit={"pitch_deg": 95}), "invalid"),
    (_raw(type="view", camera={"K": K, "R": ((2, 0, 0), (0, 1, 0), (0, 0, 1)),
                               "t": (0, 0, 1), "width": 4, "height": 4}), "invalid"),
    # finite but absurd values: refused at the boundary (finding 6 of issue 13)
    (_raw(type="drive", seq=1, smplx={"betas": [1e300]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"leye_pose": [1e38, 0, 0]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"body_pose": [0.0] * 62 + [13.0]}), "invalid"),
    (_raw(type="drive", seq=1, smplx={"transl": [0, 0, 1e9]}), "invalid"),
    (_raw(type="drive", seq=1, flame={"eyes_pose": [0, 0, 0, 0, 1e30, 0]}), "invalid"),
    (_raw(type="drive", seq=1, flame={"expr": [0.0, -11.0]}), "invalid"),
    (_raw(type="drive", seq=1, mano_left={"hand_pose": [20.0] * 6}), "invalid"),   # PCA
    (_raw(type="drive", seq=1, mano_right={"hand_pose": [9.0] * 45}), "invalid"),  # angles
    (_raw(type="view", orbit={"distance": 1e12}), "invalid"),
    (_raw(type="view", orbit={"distance": 0.0}), "invalid"),
    (_raw(type="view", orbit={"fov_y_deg": 1e-30}), "invalid"),
    (_raw(type="view", orbit={"target": (0, 1e300, 0)}), "invalid"),
    (_raw(type="view", camera={"K": K, "R": EYE, "t": (0, 0, 1e6), "width": 512,
                               "height": 512}), "invalid"),
    (_raw(type="view", camera={"K": ((1e300, 0, 256), (0, 1e300, 256), (0, 0, 1)), "R": EYE,
                               "t": (0, 0, 3), "width": 512, "height": 512}), "invalid"),
    (_raw(type="view", camera={"K": K, "R": EYE, "t": (0, 0, 3), "width": 10**9,
                               "height": 512}), "invalid"),
    (_raw(type="request", max_fps=0.001), "invalid"),
    (_raw(type="request", quality=1e-300), "invalid"),
    (_raw(type="request", width=10**6), "too_large"),
    (_raw(type="request", max_fps=1000), "too_large"),
    (_raw(type="request", codec="gif"), "invalid"),
    (_raw(type="request", background=(2, 0, 0)), "invalid"),
    (_raw(type="request", outputs=[]), "invalid"),
    (_raw(type="image", seq=1, data=b""), "invalid"),
    (_raw(type="image", seq=1, data=b"x" * (5 * 1024 * 1024)), "too_large"),
]


@pytest.mark.parametrize("data,code", BAD_CLIENT)
def test_bad_client_messages_get_the_right_code(data, code):
    with pytest.raises(ProtocolError) as err:
        decode_client(data)
    assert err.value.code == code, err.value.message
    assert err.value.message


def test_errors_say_which_message_they_answer():
    with pytest.raises(ProtocolError) as err:
        decode_client(_raw(type="drive", seq=41, smplx={"jaw_pose": [1]}))
    assert err.value.answers == {"type": "drive", "seq": 41}
    assert "jaw_pose" in err.value.message


def test_range_errors_name_the_field_and_the_range():
    with pytest.raises(ProtocolError) as err:
        decode_client(_raw(type="drive", seq=5, smplx={"betas": [1.0, 1e300]}))
    assert err.value.code == "invalid" and err.value.answers == {"type": "drive", "seq": 5}
    assert "smplx.betas" in err.value.message and "[0, 10]" in err.value.message
    with pytest.raises(ProtocolError) as err:
        decode_client(_raw(type="request", max_fps=0.001))
    assert "max_fps" in err.value.message and "[1, 60]" in err.value.message


def test_value_ranges_are_configurable_and_sent_in_welcome():
    tight = Limits(max_coefficient=2.0, max_rotation_rad=1.0, min_fps=5.0,
                   max_orbit_distance_m=3.0)
    assert decode_client(_raw(type="drive", seq=1, smplx={"betas": [3.0]})).smplx
    for raw in (_raw(type="drive", seq=1, smplx={"betas": [3.0]}),
                _raw(type="drive", seq=1, smplx={"jaw_pose": [0.8, 0.8, 0]}),
                _raw(type="request", max_fps=2.0),
                _raw(type="view", orbit={"distance": 4.0})):
        with pytest.raises(ProtocolError) as err:
            decode_client(raw, tight)
        assert err.value.code == "invalid", err.value.message
    welcome = decode_server(encode(SERVER_EXAMPLES[0].model_copy(update={"limits": tight})))
    assert welcome.limits == tight
    with pytest.raises(ValueError):
        Limits(min_fps=10, max_fps=5)


def test_size_limits_come_before_parsing_and_are_configurable():
    small = Limits(max_message_bytes=1024, max_array_elements=64)
    big = encode(Drive(seq=1, smplx={"betas": np.zeros(200)}))
    with pytest.raises(ProtocolError) as err:
        decode_client(big, small)
    assert err.value.code == "too_large"
    with pytest.raises(ProtocolError) as err:  # the array-length limit of msgpack itself
        decode_client(_raw(type="drive", seq=1, smplx={"betas": [0.0] * 100}), small)
    assert err.value.code in ("bad_message", "too_large")
    assert decode_client(big).smplx["betas"].shape == (200,)  # fine under the defaults


def test_unbatched_shapes_are_normalised():
    d = decode_client(encode(Drive(seq=0, smplx={"body_pose": np.zeros(63)},
                                   mano_left={"hand_pose": np.zeros(45)})))
    assert d.smplx["body_pose"].shape == (21, 3)
    assert d.mano_left["hand_pose"].shape == (15, 3)


# -- property tests --------------------------------------------------------------------------

_finite = st.floats(-7.0, 7.0, allow_nan=False, allow_infinity=False, width=32)  # in range
_any_finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def drives(draw):
    smplx = {}
    if draw(st.booleans()):
        smplx["jaw_pose"] = draw(st.lists(_finite, min_size=3, max_size=3))
    if draw(st.booleans()):
        smplx["expression"] = draw(st.lists(_finite, min_size=1, max_size=100))
    if draw(st.booleans()):
        n = draw(st.integers(1, 44))
        smplx["left_hand_pose"] = np.asarray(draw(st.lists(_finite, min_size=n, max_size=n)),
                                             dtype=np.float32)
    flame = {"jaw_pose": draw(st.lists(_finite, min_size=3, max_size=3))} \
        if draw(st.booleans()) else None
    return Drive(seq=draw(st.integers(0, 2**53 - 1)), smplx=smplx or None, flame=flame,
                 reset=draw(st.booleans()))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(drives())
def test_valid_drives_round_trip(drive):
    back = decode_client(encode(drive))
    assert back.seq == drive.seq and back.reset == drive.reset
    for fam, values in drive.families().items():
        got = back.families()[fam]
        assert got.keys() == values.keys()
        for k, v in values.items():
            np.testing.assert_allclose(got[k].reshape(-1), np.asarray(v, np.float64).reshape(-1))


def _size(spec) -> st.SearchStrategy[int]:
    kind, arg = spec
    if kind == "fixed":
        return st.just(math.prod(arg))
    return st.integers(1, arg if kind == "vector" else 45)


@st.composite
def wild_drives(draw):
    """Every family's fields, shape-valid, with any finite float64 (1e300 and 1e-300 too)."""
    families = {}
    for family, spec in FAMILIES.items():
        names = draw(st.lists(st.sampled_from(sorted(spec)), unique=True, max_size=len(spec)))
        families[family] = {name: draw(st.lists(_any_finite, min_size=n, max_size=n))
                            for name in names for n in [draw(_size(spec[name]))]}
    return {"type": "drive", "seq": 1, **{f: v for f, v in families.items() if v}}


def _within_limits(values: np.ndarray, name: str, lim: Limits) -> bool:
    kind = VALUE_KINDS[name]
    if kind == "hand":
        kind = "rotation" if values.size == 45 else "coefficient"
    if kind == "coefficient":
        return bool(np.abs(values).max() <= lim.max_coefficient)
    rows = np.linalg.norm(values.reshape(-1, 3), axis=1)
    return bool(rows.max() <= (lim.max_rotation_rad if kind == "rotation"
                               else lim.max_translation_m))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(wild_drives())
def test_any_finite_drive_is_refused_cleanly_or_within_limits(raw):
    try:
        drive = decode_client(msgpack.packb(raw, use_bin_type=True))
    except ProtocolError as exc:
        assert exc.code == "invalid" and exc.message
        return
    for family, values in drive.families().items():
        for name, arr in values.items():
            assert np.isfinite(arr).all() and _within_limits(arr, name, Limits()), \
                (family, name, arr)


@settings(max_examples=200, deadline=None)
@given(st.fixed_dictionaries({}, optional={
    "distance": _any_finite, "fov_y_deg": _any_finite, "yaw_deg": _any_finite,
    "target": st.tuples(_any_finite, _any_finite, _any_finite)}),
    st.one_of(st.none(), _any_finite))
def test_any_finite_view_or_rate_is_refused_cleanly_or_within_limits(orbit, max_fps):
    lim = Limits()
    try:
        view = decode_client(_raw(type="view", orbit=orbit))
        o = view.orbit
        assert lim.min_orbit_distance_m <= o.distance <= lim.max_orbit_distance_m
        assert lim.min_fov_deg <= o.fov_y_deg <= lim.max_fov_deg
        assert o.target is None or math.hypot(*o.target) <= lim.max_position_m
    except ProtocolError as exc:
        assert exc.code == "invalid"
    try:
        req = decode_client(_raw(type="request", max_fps=max_fps))
        assert req.max_fps is None or lim.min_fps <= req.max_fps <= lim.max_fps
    except ProtocolError as exc:
        assert exc.code in ("invalid", "too_large")


_vec3 = st.tuples(_any_finite, _any_finite, _any_finite)


@settings(max_examples=200, deadline=None)
@given(st.tuples(_vec3, _vec3, _vec3), _vec3, st.integers(-10, 10**9), st.integers(-10, 10**9),
       st.booleans())
def test_any_finite_camera_is_refused_cleanly_or_within_limits(K, t, width, height, proper):
    lim = Limits()
    K = ((K[0][0], K[0][1], K[0][2]), (0.0, K[1][1], K[1][2]), (0.0, 0.0, 1.0)) if proper else K
    camera = {"K": K, "R": EYE, "t": t, "width": width, "height": height}
    try:
        view = decode_client(_raw(type="view", camera=camera))
    except ProtocolError as exc:
        assert exc.code == "invalid"
        return
    c = view.camera
    assert 0 < c.width <= lim.max_camera_size and 0 < c.height <= lim.max_camera_size
    assert math.hypot(*c.t) <= lim.max_position_m
    fov = math.degrees(2 * math.atan(c.height / (2 * c.K[1][1])))
    assert lim.min_fov_deg <= fov <= lim.max_fov_deg


_msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**63 - 1) | st.floats() | st.text(max_size=20)
    | st.binary(max_size=64),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner,
                                                                max_size=5),
    max_leaves=20)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(["type", "seq", "smplx", "flame", "orbit", "camera",
                                        "data", "outputs", "width", "t", "token", "reset"]),
                       _msgpack_values, max_size=6),
       st.sampled_from(sorted(CLIENT_TYPES)))
def test_random_messages_fail_only_with_protocol_errors(fields, kind):
    fields = {"type": kind, **fields} if "type" not in fields else fields
    try:
        decode_client(msgpack.packb(fields, use_bin_type=True))
    except ProtocolError as exc:
        assert exc.code in ("bad_message", "invalid", "too_large") and exc.message


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=256))
def test_random_bytes_fail_only_with_protocol_errors(data):
    try:
        decode_client(data)
    except ProtocolError as exc:
        assert exc.code in ("bad_message", "invalid", "too_large")
