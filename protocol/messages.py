"""The message types, defined once: the server, the Python client and (through the generated
JavaScript module) the browser page all use these.

Every message is a msgpack map with a ``type``. Client -> server: ``hello``, ``drive``,
``view``, ``request``, ``image``, ``ping``, ``voice``. Server -> client: ``welcome``, ``frame``,
``error``, ``stats``, ``pong``, ``presence`` (rooms), ``tracked`` (answers ``image``),
``voice``. Unknown fields are errors, so a typo never passes silently. Minor version 1 (rooms)
adds only optional fields, left out of plain sessions' messages, so a client of minor version 0
keeps working there. Minor version 2 adds ``hello.name``, ``avatar.expression_names`` (left out
when the avatar names none), ``tracked``, which only a client that sends images gets, the
``voice`` message and the optional ``t_capture`` of drives and frames (one clock: the
performer's). Minor version 4 adds ``welcome.voice`` (the voice bounds a performer encodes
within), ``image.t_capture`` (a tracked webcam frame's drive carries it) and ``hello.voice_mix``
(one mixed voice instead of each seat's).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .errors import ProtocolError
from .limits import DEFAULT_LIMITS, Limits
from .names import display_name
from .params import validate_family

PROTOCOL_VERSION = 1
PROTOCOL_MINOR = 4  # 1: rooms (hello.role/seat, welcome.room/minor, presence)
#                     2: hello.name, avatar.expression_names, tracked, voice, t_capture,
#                        avatar (a seat's avatar replaced in place)
#                     3: presence seats' speaking, voice.level_dbov
#                     4: welcome.voice (the server's voice bounds), image.t_capture,
#                        hello.voice_mix
MAX_SEATS = 16      # seat indices on the wire; server settings bound a room's seats further
MAX_SEQ = 2**53 - 1  # exact in a JavaScript number
MAX_EXPRESSION_NAMES = 100  # as many as an expression vector may hold (params.FAMILIES)

OUTPUTS = ("rgb", "alpha", "depth")
CODECS = ("jpeg", "png", "h264")
IMAGE_FORMATS = ("jpeg", "png")

Seq = Annotated[int, Field(ge=0, le=MAX_SEQ)]
SeatIndex = Annotated[int, Field(ge=0, lt=MAX_SEATS)]
# Seconds on the performer's own monotonic clock (performance.now() / 1000, time.monotonic()):
# when what a drive or a voice packet carries was captured. The server never compares it with
# its own clock; it hands it back on what shows or plays it.
MAX_CAPTURE_TIME = 1e9  # seconds: a capture time is at most this
CaptureTime = Annotated[float, Field(ge=0, le=MAX_CAPTURE_TIME, allow_inf_nan=False)]
MAX_VOICE_BYTES = 1276  # one Opus frame of the largest (1275 B) and its TOC byte
Role = Literal["perform", "watch"]
Vec3 = tuple[float, float, float]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True,
                              allow_inf_nan=False)


def _limits(info: ValidationInfo) -> Limits:
    return (info.context or {}).get("limits", DEFAULT_LIMITS)


def _within(name: str, value: float, low: float, high: float, setting: str) -> None:
    """A ValueError naming the range (code ``invalid``) when ``value`` is outside it."""
    if not low <= value <= high:
        raise ValueError(f"{name} {value:.6g} is out of range [{low:.6g}, {high:.6g}] "
                         f"(limits.{setting})")


def _norm(v: Vec3) -> float:
    return math.hypot(*v)


# -- client -> server --------------------------------------------------------------------


class Hello(_Message):
    """First message of a session (optional when the token came in the URL or a header)."""

    type: Literal["hello"] = "hello"
    version: int = PROTOCOL_VERSION
    token: str | None = Field(None, max_length=512)
    client: str | None = Field(None, max_length=200)  # the software, never shown to others
    role: Role | None = None       # rooms: perform a seat or watch (default: the token's)
    seat: SeatIndex | None = None  # rooms: the seat to perform (or to follow, watching)
    name: str | None = None        # the display name others see (protocol/names.py)
    voice: bool | None = None      # rooms (minor 2): hear the other seats as `voice` messages
    voice_mix: bool | None = None  # rooms (minor 4), watching: hear one mix of every seat
    #                                instead (`voice` messages without a seat); implies voice

    @field_validator("name")
    @classmethod
    def _name(cls, value: str | None, info: ValidationInfo) -> str | None:
        return None if value is None else display_name(value, _limits(info).max_name_chars)


class Drive(_Message):
    """Body-model parameters for the next frame; any subset of any family (partial update).

    ``reset``: every parameter goes back to the rest pose before these are applied.
    """

    type: Literal["drive"] = "drive"
    seq: Seq
    smplx: dict[str, Any] | None = None
    flame: dict[str, Any] | None = None
    mano_left: dict[str, Any] | None = None
    mano_right: dict[str, Any] | None = None
    reset: bool = False
    t_capture: CaptureTime | None = None  # when its source (camera frame, take) was captured

    @field_validator("smplx", "flame", "mano_left", "mano_right", mode="after")
    @classmethod
    def _arrays(cls, value: Any, info: ValidationInfo) -> dict[str, np.ndarray] | None:
        if value is None:
            return None
        try:
            return validate_family(info.field_name, value, _limits(info))
        except ProtocolError as exc:
            raise ValueError(exc.message) from exc

    def families(self) -> dict[str, dict[str, np.ndarray]]:
        return {name: getattr(self, name) for name in ("smplx", "flame", "mano_left",
                                                       "mano_right")
                if getattr(self, name) is not None}


class Orbit(_Message):
    """A camera on a sphere around ``target`` (the avatar's chest when None), looking at it."""

    yaw_deg: float = Field(0.0, ge=-360, le=360)
    pitch_deg: float = Field(0.0, ge=-89, le=89)
    distance: float = 2.7     # metres, within limits.min/max_orbit_distance_m
    fov_y_deg: float = 30.0   # within limits.min/max_fov_deg
    target: Vec3 | None = None

    @field_validator("distance")
    @classmethod
    def _distance(cls, value: float, info: ValidationInfo) -> float:
        lim = _limits(info)
        _within("distance", value, lim.min_orbit_distance_m, lim.max_orbit_distance_m,
                "min_orbit_distance_m / max_orbit_distance_m")
        return value

    @field_validator("fov_y_deg")
    @classmethod
    def _fov(cls, value: float, info: ValidationInfo) -> float:
        lim = _limits(info)
        _within("fov_y_deg", value, lim.min_fov_deg, lim.max_fov_deg, "min_fov_deg / max_fov_deg")
        return value

    @field_validator("target")
    @classmethod
    def _target(cls, value: Vec3 | None, info: ValidationInfo) -> Vec3 | None:
        if value is not None:
            lim = _limits(info).max_position_m
            _within("target distance from the origin", _norm(value), 0, lim, "max_position_m")
        return value


class CameraSpec(_Message):
    """A full OpenCV camera: world -> camera ``[R|t]``, intrinsics ``K``, image size."""

    K: tuple[Vec3, Vec3, Vec3]
    R: tuple[Vec3, Vec3, Vec3]
    t: Vec3   # |t| is the camera centre's distance from the origin (R is a rotation)
    width: int = Field(gt=0)    # at most limits.max_camera_size
    height: int = Field(gt=0)

    @field_validator("width", "height")
    @classmethod
    def _size(cls, value: int, info: ValidationInfo) -> int:
        _within(info.field_name, value, 1, _limits(info).max_camera_size, "max_camera_size")
        return value

    @field_validator("t")
    @classmethod
    def _position(cls, value: Vec3, info: ValidationInfo) -> Vec3:
        lim = _limits(info).max_position_m
        _within("camera distance from the origin", _norm(value), 0, lim, "max_position_m")
        return value

    @model_validator(mode="after")
    def _proper(self, info: ValidationInfo) -> CameraSpec:
        R = np.asarray(self.R)
        if (np.abs(R).max() > 1 + 1e-3 or abs(np.linalg.det(R) - 1) > 1e-3
                or not np.allclose(R @ R.T, np.eye(3), atol=1e-3)):
            raise ValueError("R must be a rotation matrix (orthonormal, det +1)")
        K = np.asarray(self.K)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise ValueError("K must have positive focal lengths and a last row [0, 0, 1]")
        # Sane intrinsics: square-ish pixels, little skew, the principal point near the image.
        fx, fy = K[0, 0], K[1, 1]
        if not (0.5 <= fx / fy <= 2 and abs(K[0, 1]) <= fx
                and abs(K[0, 2] - self.width / 2) <= self.width
                and abs(K[1, 2] - self.height / 2) <= self.height):
            raise ValueError("K must have fx / fy in [0.5, 2], |skew| <= fx and the principal "
                             "point within one image size of the image centre")
        lim = _limits(info)
        fov = math.degrees(2 * math.atan(self.height / (2 * fy)))
        _within("vertical field of view (deg)", fov, lim.min_fov_deg, lim.max_fov_deg,
                "min_fov_deg / max_fov_deg")
        return self


class View(_Message):
    """Where to look from: an orbit or a full camera (exactly one)."""

    type: Literal["view"] = "view"
    orbit: Orbit | None = None
    camera: CameraSpec | None = None
    moving: bool = False  # the user is dragging: the server may lower JPEG quality

    @model_validator(mode="after")
    def _one(self) -> View:
        if (self.orbit is None) == (self.camera is None):
            raise ValueError("a view has exactly one of 'orbit' and 'camera'")
        return self


class Request(_Message):
    """What to render and how to send it; fields not sent keep their current value."""

    type: Literal["request"] = "request"
    outputs: list[Literal["rgb", "alpha", "depth"]] | None = Field(None, min_length=1)
    width: int | None = Field(None, ge=16)
    height: int | None = Field(None, ge=16)
    background: Vec3 | None = None
    sh_degree: int | None = Field(None, ge=0, le=3)
    quality: float | None = Field(None, ge=0.01, le=1)  # fraction of the Gaussians rendered
    jpeg_quality: int | None = Field(None, ge=1, le=100)
    codec: Literal["jpeg", "png", "h264"] | None = None
    max_fps: float | None = Field(None, gt=0)  # within limits.min_fps .. limits.max_fps

    @field_validator("background")
    @classmethod
    def _unit(cls, value: Vec3 | None) -> Vec3 | None:
        if value is not None and not all(0 <= c <= 1 for c in value):
            raise ValueError("background values must be in [0, 1]")
        return value

    @model_validator(mode="after")
    def _within(self, info: ValidationInfo) -> Request:
        lim = _limits(info)
        if self.width is not None and self.width > lim.max_width:
            raise ValueError(f"width {self.width} exceeds the limit {lim.max_width}")
        if self.height is not None and self.height > lim.max_height:
            raise ValueError(f"height {self.height} exceeds the limit {lim.max_height}")
        if self.max_fps is not None and self.max_fps > lim.max_fps:
            raise ValueError(f"max_fps {self.max_fps} exceeds the limit {lim.max_fps}")
        if self.max_fps is not None and self.max_fps < lim.min_fps:
            raise ValueError(f"max_fps {self.max_fps:.6g} is out of range "
                             f"[{lim.min_fps:.6g}, {lim.max_fps:.6g}] (limits.min_fps)")
        return self


class Image(_Message):
    """An encoded webcam frame for server-side tracking."""

    type: Literal["image"] = "image"
    seq: Seq
    format: Literal["jpeg", "png"] = "jpeg"
    data: bytes
    t_capture: CaptureTime | None = None  # (minor 4) when the camera took it: the drive the
    #                                       server tracks from it carries it (lip sync)

    @field_validator("data")
    @classmethod
    def _size(cls, value: bytes, info: ValidationInfo) -> bytes:
        lim = _limits(info).max_image_bytes
        if not value:
            raise ValueError("data is empty")
        if len(value) > lim:
            raise ValueError(f"image of {len(value)} bytes exceeds the limit {lim}")
        return value


class Ping(_Message):
    type: Literal["ping"] = "ping"
    t: float = 0.0  # client clock, echoed in pong


# -- server -> client --------------------------------------------------------------------


class AvatarInfo(_Message):
    id: str
    name: str
    num_gaussians: int
    sh_degree: int
    owner: str | None = None
    metadata: dict[str, Any] = Field(default_factory=dict)
    # What each expression coefficient means, in order (the body model's rig); None: unnamed.
    expression_names: list[Annotated[str, Field(max_length=64)]] | None = Field(
        None, max_length=MAX_EXPRESSION_NAMES)


class RoomWelcome(_Message):
    """The room a participant joined, and as what."""

    id: str
    name: str
    role: Role
    seat: SeatIndex | None = None  # the seat performed (None: watching)


class EncodersInfo(_Message):
    """The server's encoders: on a GPU server nvJPEG and NVENC, else the CPU ones."""

    jpeg: Literal["nvjpeg", "opencv"]
    h264: Literal["h264_nvenc", "libx264"]


class Framing(_Message):
    """Where to look to see the scene at rest whole (a page's default view), and its face.

    Orbit around ``target`` at ``distance`` (at ``fov_y_deg``, a square frame) to see every
    seat's upper body and hands; zooming in goes toward ``face`` (the performed seat's head, or
    seat 0's), and no closer than ``min_distance`` from it, where the whole head still fits.
    """

    target: Vec3
    distance: float = Field(gt=0)
    fov_y_deg: float = Field(gt=0, lt=180)
    face: Vec3
    min_distance: float = Field(gt=0)


class VoiceBounds(_Message):
    """What a performer's voice may carry here (the server's voice_max_bitrate and
    voice_max_packet_bytes): an encoder set within them loses no packet to the bounds."""

    max_bitrate: int = Field(gt=0)       # bits/s of Opus payload per seat
    max_packet_bytes: int = Field(gt=0)  # one Opus packet


class Welcome(_Message):
    type: Literal["welcome"] = "welcome"
    version: int = PROTOCOL_VERSION
    minor: int | None = None  # PROTOCOL_MINOR in room sessions (left out of plain ones)
    session: str
    avatar: AvatarInfo  # a room: the performed seat's avatar (watching: seat 0's)
    limits: Limits
    codecs: list[str]
    request: Request  # the effective render request (defaults filled in)
    room: RoomWelcome | None = None
    encoders: EncodersInfo | None = None  # what encodes the frames (servers that report it)
    framing: Framing | None = None  # the default view of the scene at rest (servers that send it)
    voice: VoiceBounds | None = None  # rooms (minor 4): the bounds on a performer's voice


class SeatPresence(_Message):
    index: SeatIndex
    avatar: str
    performer: str | None = None  # the performer's client name; None: the seat is free
    holding: bool = False         # performer gone: the last pose held, then easing to rest
    speaking: bool = False        # its voice is loud now (sent again when that changes)


class Presence(_Message):
    """Who is in a room: sent after ``welcome``, to everyone on each join and leave, and when
    who speaks changes (at most once per ``voice_presence_interval_s``)."""

    type: Literal["presence"] = "presence"
    room: str
    seats: list[SeatPresence]
    viewers: int
    event: Literal["join", "leave", "update"] = "update"
    who: str | None = None   # the client name that joined or left
    role: Role | None = None


class Tracked(_Message):
    """What the tracker found in image ``seq``: the groups seen (face, hands, pose); ``found``
    is False when it saw no person, and then the avatar holds its last pose."""

    type: Literal["tracked"] = "tracked"
    seq: Seq
    found: bool
    seen: dict[str, bool] = Field(default_factory=dict)


class AvatarReplaced(_Message):
    """The avatar ``avatar.id`` was replaced in place (the trained demo built behind its
    stand-in): the frames after this message show it on ``seats``. Sent to every participant
    of a scene that shows it, plain sessions included; the connection stays."""

    type: Literal["avatar"] = "avatar"
    avatar: AvatarInfo
    seats: list[SeatIndex]


class Timings(_Message):
    """Milliseconds per stage of this frame (track is 0 unless a webcam frame drove it)."""

    track: float = 0.0
    pose: float = 0.0
    render: float = 0.0
    encode: float = 0.0


class Frame(_Message):
    type: Literal["frame"] = "frame"
    seq: int          # seq of the newest drive (or image) this frame reflects; -1: none yet
    frame: int        # this session's frame counter
    codec: Literal["jpeg", "png", "h264"]
    width: int
    height: int
    data: bytes
    depth: bytes | None = None  # 16-bit PNG, millimetres, when depth was requested
    keyframe: bool = True       # h264: the stream can start here
    timings: Timings = Field(default_factory=Timings)
    preview: bool = False       # a moving view's cheaper frame; a full one follows when still
    t_capture: float | None = None  # the t_capture of the drive it shows (seq), when it had one


class Answers(_Message):
    type: str | None = None
    seq: int | None = None


class Error(_Message):
    type: Literal["error"] = "error"
    code: str
    message: str
    answers: Answers | None = None  # the message this error answers, when known


class Stats(_Message):
    type: Literal["stats"] = "stats"
    fps: float
    frames: int
    dropped: int          # frames not sent because a newer input superseded them
    coalesced: int        # drives merged into a later one before rendering
    bytes_per_s: float
    render_ms: float      # recent median
    sessions: int


class Pong(_Message):
    type: Literal["pong"] = "pong"
    t: float


class Voice(_Message):
    """One Opus packet (RFC 6716, 48 kHz) of a seat's voice. A performer sends its own (for its
    seat); the server sends each seat's to the room's other participants, ``seat`` set, delayed
    to match the picture. Packets the server cannot parse as Opus are dropped and counted."""

    type: Literal["voice"] = "voice"
    seq: Seq                               # the sender's packet counter: gaps are losses
    data: Annotated[bytes, Field(min_length=1, max_length=MAX_VOICE_BYTES)]
    t_capture: CaptureTime | None = None   # its first sample's capture time
    seat: SeatIndex | None = None          # server -> client: whose voice
    level_dbov: Annotated[float, Field(ge=-127, le=0)] | None = None  # RFC 6464's audio level


ClientMessage = Annotated[Hello | Drive | View | Request | Image | Ping | Voice,
                          Field(discriminator="type")]
ServerMessage = Annotated[Welcome | Frame | Error | Stats | Pong | Presence | Tracked | Voice
                          | AvatarReplaced, Field(discriminator="type")]
CLIENT_TYPES = {m.model_fields["type"].default: m for m in (Hello, Drive, View, Request, Image,
                                                             Ping, Voice)}
SERVER_TYPES = {m.model_fields["type"].default: m for m in (Welcome, Frame, Error, Stats, Pong,
                                                             Presence, Tracked, Voice,
                                                             AvatarReplaced)}
