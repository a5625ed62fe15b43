"""Server settings: defaults here, then a TOML/JSON file, then ``TELESPLAT_<FIELD>`` env vars.

Every field is documented; ``docs/server.md`` has the same table. Nested ``limits`` come from a
``[limits]`` table in the file, or as JSON in ``TELESPLAT_LIMITS`` (merged over the file's).
"""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from avatar_core.gaussians.validate import GaussianRanges
from avatar_core.threads import (
    THREADS_VAR,
    RenderThreads,
    machine_threads,
    render_threads,
    usable_cores,
)
from protocol import Limits

ENV_PREFIX = "TELESPLAT_"
NESTED = frozenset({"limits", "gaussian_ranges"})  # tables in the file, JSON in the env


def default_data_dir() -> Path:
    return Path.home() / ".cache" / "telesplat" / "server"


DEFAULT_PORTS = {"http": 80, "https": 443}


def cors_origin(text: str) -> str:
    """A web origin as a browser sends it in ``Origin`` (scheme and host lower case, no default
    port), from ``scheme://host[:port]``; ValueError naming what is wrong otherwise."""
    problem = f"cors_origins: {text!r} is not an origin (http[s]://host[:port], no path)"
    try:
        parts = urlsplit(text.strip())
        port = parts.port
    except ValueError:
        raise ValueError(problem) from None
    if (parts.scheme.lower() not in DEFAULT_PORTS or not parts.hostname or parts.username
            or parts.password or parts.path or parts.query or parts.fragment
            or text.strip().endswith(("?", "#"))):
        raise ValueError(problem)
    scheme, host = parts.scheme.lower(), parts.hostname.lower()
    if ":" in host:
        host = f"[{host}]"
    suffix = "" if port is None or port == DEFAULT_PORTS[scheme] else f":{port}"
    return f"{scheme}://{host}{suffix}"


class Settings(BaseModel):
    """Everything the server reads at start-up."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    host: str = Field("127.0.0.1", description="Interface to listen on (0.0.0.0: all).")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0: any free port).")
    data_dir: Path = Field(default_factory=default_data_dir,
                           description="Where avatars, tokens and job data live.")
    max_sessions: int = Field(8, ge=1, description="Concurrent streaming sessions; past it a "
                                                   "new session gets error 'busy' and is closed.")
    max_sessions_per_user: int = Field(
        4, ge=1, description="Concurrent streaming sessions per token subject (admin tokens "
                             "are exempt); past it a new session gets error 'busy', close "
                             "code 4429.")
    max_sessions_per_invitation: int = Field(
        4, ge=1, description="Concurrent sessions (WebSocket and WebRTC) one room invitation "
                             "may hold; past it 'busy', close code 4429 (WHEP/WHIP 429).")
    reserved_sessions: int = Field(
        2, ge=0, description="Of max_sessions, how many only token holders (room owners, "
                             "admins) may take: invitation holders get busy (1013, WHEP 503) "
                             "once max_sessions - reserved_sessions are open.")
    hello_timeout_s: float = Field(
        5.0, gt=0, description="Seconds a WebSocket without a token in its header or URL may "
                               "take to send its 'hello'; then error 'unauthorized', close 4408.")
    hello_max_bytes: int = Field(
        4096, ge=1024, description="Largest first message before authentication, bytes; checked "
                                   "on the frame's length before any decoding (close 4413).")
    max_unauthenticated: int = Field(
        32, ge=1, description="WebSocket connections waiting to authenticate, in total; past it "
                              "a new one gets error 'busy', close code 1013.")
    max_unauthenticated_per_address: int = Field(
        8, ge=1, description="WebSocket connections waiting to authenticate from one client "
                             "address; past it error 'busy', close code 4429.")
    max_message_objects: int = Field(
        16384, ge=256, description="msgpack objects in one client message, counted before it "
                                   "is unpacked (bounds the decode time); past it 'too_large'.")
    decode_offload_bytes: int = Field(
        64 * 1024, ge=0, description="Client messages of at least this many bytes are decoded "
                                     "in a worker thread, off the event loop.")
    max_inbound_bytes_per_s: float = Field(
        16 * 2**20, gt=0, description="Bytes per second one session may send (token bucket, "
                                      "burst max(16 MiB, limits.max_message_bytes)); past it "
                                      "the session's socket is read more slowly (backpressure).")
    ticket_ttl_s: float = Field(
        30.0, gt=0, description="Seconds a stream ticket (POST /v1/stream/tickets) stays valid; "
                                "each opens one /v1/stream?ticket=... connection.")
    max_tickets_per_user: int = Field(
        16, ge=1, description="Unspent, unexpired stream tickets one token subject may hold; "
                              "past it POST /v1/stream/tickets is 429.")
    tokens_reload_interval_s: float = Field(
        1.0, ge=0, description="How often, at most, the token file's mtime and size are "
                               "checked; a change (e.g. telesplat serve --issue-token) is "
                               "loaded without a restart.")
    limits: Limits = Field(default_factory=Limits,
                           description="Per-session protocol limits (sent in 'welcome').")
    jpeg_quality: int = Field(85, ge=1, le=100, description="JPEG quality of still views.")
    jpeg_quality_moving: int = Field(60, ge=1, le=100,
                                     description="JPEG quality while view.moving is set.")
    moving_view_settle_ms: float = Field(
        150.0, ge=0, le=10_000, description="A view whose camera changed twice within this "
                                            "many ms (or whose view.moving is set) is moving: "
                                            "its frames are previews (moving_view_scale, "
                                            "moving_view_quality, jpeg_quality_moving). Still "
                                            "this long: one full-quality frame follows.")
    moving_view_scale: float = Field(
        0.5, gt=0, le=1, description="A moving view renders at this fraction of the asked "
                                     "width and height, upscaled back before encoding "
                                     "(1: full resolution).")
    moving_view_quality: float = Field(
        1.0, ge=0.01, le=1, description="A moving view renders at most this fraction of the "
                                        "Gaussians (the render budget; 1: all of them).")
    default_width: int = Field(512, ge=16, description="Frame width until a request sets it.")
    default_height: int = Field(512, ge=16, description="Frame height until a request sets it.")
    default_max_fps: float = Field(30.0, gt=0, description="Per-session frame-rate cap until "
                                                           "a request sets it (<= limits.max_fps).")
    frame_burst: int = Field(1, ge=1, le=8, description="Frames a session may start back to "
                                                    "back under its max_fps, which caps the "
                                                    "average rate (1: a strict 1/max_fps "
                                                    "interval between frames).")
    auth: Literal["local", "tokens"] = Field(
        "local", description="local: an admin token for subject 'local' is issued and printed "
                             "at start-up; tokens: only tokens already in the token file.")
    tokens_file: Path | None = Field(None, description="Token store (JSON, sha256 hashes); "
                                                       "default data_dir/tokens.json.")
    cors_origins: list[str] = Field(
        default_factory=list, description="Web origins (scheme://host[:port]) whose pages may "
                                          "call the REST and WHEP/WHIP endpoints from a "
                                          "browser (CORS; no credentials mode: tokens travel "
                                          "in the Authorization header). None by default: no "
                                          "CORS headers at all. '*' alone allows any origin "
                                          "(docs/security.md). TELESPLAT_CORS_ORIGINS is "
                                          "comma-separated or a JSON list.")
    cors_max_age_s: int = Field(
        600, ge=0, le=86400, description="Seconds a browser may cache a CORS preflight's "
                                         "answer (Access-Control-Max-Age).")
    max_upload_bytes: int = Field(512 * 2**20, ge=1024,
                                  description="Largest avatar upload (zip) accepted, bytes.")
    demo_avatar: str = Field("synthetic", description="Avatar registered at start-up, owner "
                                                      "'public': synthetic, trained, none, or "
                                                      "a package path. trained never holds up "
                                                      "the start: until the trained demo is "
                                                      "built (a background job, GET /v1/demo) "
                                                      "the synthetic one stands in.")
    demo_cache_dir: Path | None = Field(
        None, description="Where the trained demo avatar is built and cached (None: "
                          "~/.cache/telesplat/demo-avatar-vN, as `telesplat demo-avatar`).")
    demo_build_recipe: dict[str, Any] | None = Field(
        None, description="The trained demo's recipe (avatar_core/demo.py DemoRecipe fields: "
                          "motions, resolution, frames, preset, iterations); None: the "
                          "default. A smaller one belongs in its own demo_cache_dir.")
    body_models: Path | None = Field(
        None, description="Folder of the body-model files under their official names "
                          "(SMPLX_NEUTRAL.npz, smplx_vert_segmentation.json, MANO_*.pkl, "
                          "FLAME_NEUTRAL.pkl, ...), for avatars, training jobs and tracking "
                          "bound to licensed models; None: only the synthetic family. "
                          "Also TELESPLAT_BODY_MODELS, which every command reads.")
    render_threads: int | None = Field(
        None, ge=1, le=64, description="Render worker threads shared by all sessions (see "
                                       "fair_share). None (auto): one per usable core "
                                       "(affinity mask and cgroup quota; TELESPLAT_THREADS "
                                       "overrides the count), or what torch_threads leaves; "
                                       "the choice is logged at start-up.")
    fair_share: Literal["time", "frames"] = Field(
        "time", description="How render threads are shared. time: the waiting session with the "
                            "least recent render time goes first, and with N sessions active "
                            "each is paced to at most render_threads/N of the render time "
                            "(alone, none is held back); frames: first come first served, "
                            "equal frame rates whatever a frame costs.")
    fair_share_window_s: float = Field(
        2.0, gt=0, le=60, description="fair_share time: half-life of the recent render time, "
                                      "and how long a session counts as active after its "
                                      "last frame.")
    max_tile_pairs: int = Field(
        2**20, ge=0, description="Most (Gaussian, tile) pairs one frame composites (its "
                                     "render cost, counted from the projection before anything "
                                     "per pair is allocated); past it the least important "
                                     "splats are dropped until the rest fit (the frame is "
                                     "degraded, stats count it). Bounds a frame's time and "
                                     "memory whatever the avatar.")
    max_avatar_tile_pairs: int = Field(
        2**20, ge=0, description="Most (Gaussian, tile) pairs a frame of an avatar at its "
                                     "rest pose, from the default orbit at the largest output "
                                     "(limits.max_width x max_height), may need; checked at "
                                     "upload (422) and when a stored avatar is opened.")
    render_batch_views: int | None = Field(
        None, ge=1, le=256, description="Most views of one room state (same request) rendered "
                                        "in one rasterizer call while they wait together; "
                                        "1: no batching; None (auto): 32 when renders go to "
                                        "gsplat (CUDA), else 1 (the cpu kernels gain nothing).")
    encoders: Literal["auto", "cpu"] = Field(
        "auto", description="Frame encoders. auto: nvJPEG (torchvision on CUDA) and NVENC "
                            "(PyAV's h264_nvenc) where a probe at start-up shows they work, "
                            "else OpenCV JPEG and libx264; cpu: always the CPU ones. The "
                            "choice is reported in welcome.encoders.")
    track_threads: int = Field(1, ge=1, le=64, description="Webcam-tracking worker threads "
                                                           "shared by all sessions.")
    torch_threads: int | None = Field(
        None, ge=1, le=64,
        description="torch / numba threads per render worker. None (auto): the usable cores "
                    "divided by render_threads; with both auto, 1 per frame while the workers "
                    "are all busy and a lone frame's kernels on every core "
                    "(avatar_core/threads.py render_threads). render_threads x torch_threads "
                    "above the cores oversubscribes them (logged as such); training jobs "
                    "run niced in their own process.")
    send_buffer_bytes: int = Field(
        64 * 1024, ge=0, description="Kernel send buffer per connection (SO_SNDBUF; Linux "
                                     "doubles it); bounds how many frames a slow client can "
                                     "have queued. 0: the OS default (autotuned, megabytes).")
    stats_interval_s: float = Field(2.0, gt=0, description="Seconds between 'stats' messages.")
    warmup: bool = Field(True, description="Render one frame at start-up, behind the open "
                                          "server (numba compiles once).")
    backend: Literal["auto", "torch", "cpu", "gsplat"] = Field(
        "auto", description="Rasterizer backend (auto: gsplat on CUDA, else cpu).")
    job_threads: int = Field(
        2, ge=1, le=64, description="torch / numba / BLAS threads of each training process "
                                    "(and of the trained demo's capture process). Its pools "
                                    "wait passively, so 2 trains faster than 1 also beside "
                                    "other work (docs/benchmarks.md, \"First run\").")
    job_nice: int = Field(
        10, ge=0, le=19, description="CPU priority increment of each training process (and "
                                     "of the trained demo's capture): live sessions go first. "
                                     "On a machine busy with other work a niced build gets "
                                     "little CPU; 0 builds at normal priority.")
    job_max_attempts: int = Field(
        3, ge=1, description="Runs of one training job (retries after a killed or crashed "
                             "training process and server restarts included) before it fails; "
                             "a resume grants as many more.")
    job_max_active_per_user: int = Field(
        4, ge=1, description="Queued + running training jobs per user; past it a submission "
                             "is 429 (admins exempt).")
    job_max_stored_per_user: int = Field(
        200, ge=1, description="Training jobs kept per user, finished ones included; past it a "
                               "submission is 429 until some are deleted (admins exempt).")
    max_unpack_ratio: float = Field(
        100.0, ge=1, description="Largest unpacked / packed size ratio of one member of an "
                                 "uploaded zip or npz that unpacks to more than 1 MiB; past it "
                                 "the upload is refused as a decompression bomb (413).")
    max_npz_array_bytes: int = Field(
        512 * 2**20, ge=1024, description="Largest array of an uploaded npz (avatar Gaussians, "
                                          "dataset parameters), unpacked, from its declared "
                                          "shape before anything is read (422 / 400).")
    max_npz_bytes: int = Field(
        1 * 2**30, ge=1024, description="Largest total of the arrays of one uploaded npz, "
                                        "unpacked; bounds the memory one upload can take.")
    max_dataset_unpacked_bytes: int = Field(
        8 * 2**30, ge=1024, description="Largest uploaded dataset archive, unpacked (413).")
    max_dataset_member_bytes: int = Field(
        1 * 2**30, ge=1024, description="Largest file of an uploaded dataset archive, "
                                        "unpacked (413).")
    max_dataset_files: int = Field(
        100_000, ge=1, description="Most members of an uploaded dataset archive (413).")
    max_dataset_json_bytes: int = Field(
        16 * 2**20, ge=1024, description="Largest .json file of an uploaded dataset archive "
                                         "(dataset.json, cameras.json, splits.json are parsed "
                                         "whole; 413).")
    enroll_max_video_bytes: int = Field(
        256 * 2**20, ge=1024, description="Largest enrollment video (POST /v1/jobs, part "
                                          "'video'), counted as it arrives (413).")
    enroll_min_duration_s: float = Field(
        3.0, ge=0, description="Shortest enrollment video, seconds (from its packets; 422).")
    enroll_max_duration_s: float = Field(
        120.0, gt=0, description="Longest enrollment video, seconds (from its packets, "
                                 "refused while they are read; 413).")
    enroll_min_side_px: int = Field(
        64, ge=1, description="Smallest shorter side of an enrollment video's picture (422).")
    enroll_max_side_px: int = Field(
        4096, ge=16, description="Largest longer side of an enrollment video's picture "
                                 "(413); larger allowed ones are downscaled to the "
                                 "enrollment's resolution.")
    enroll_max_packets: int = Field(
        20_000, ge=1, description="Most video packets (about frames) the probe of an "
                                  "enrollment video reads (413).")
    enroll_max_decode_fps: float = Field(
        15.0, gt=0, le=240, description="Frames a second an enrollment keeps from its video; "
                                        "the others are skipped while decoding.")
    enroll_max_frames: int = Field(
        1800, ge=1, description="Most frames an enrollment decodes and keeps (413 at "
                                "submission; the job fails past it if the video lied).")
    enroll_max_decoded_bytes: int = Field(
        1024 * 2**20, ge=1024, description="Most bytes an enrollment's kept frames unpack to "
                                           "(RGB, at the enrollment's resolution; 413).")
    enroll_max_iterations: int = Field(
        30_000, ge=1, description="Most training iterations an enrollment job may ask (422).")
    enroll_max_resolution: int = Field(
        1024, ge=32, description="Largest resolution and track_size (px, longer side) an "
                                 "enrollment job may ask (422).")
    enroll_max_fit_iterations: int = Field(
        5_000, ge=0, description="Most shape-fit iterations an enrollment job may ask (422).")
    max_avatars_per_user: int = Field(
        100, ge=1, description="Avatars one user may own (uploads; trained avatars count "
                               "too); past it an upload is 429 (admins exempt).")
    max_stored_bytes_per_user: int = Field(
        20 * 2**30, ge=1024, description="Bytes one user may store: their avatars plus their "
                                         "jobs' folders (uploaded datasets, checkpoints); an "
                                         "upload past it is 413 (admins exempt).")
    max_rooms_per_user: int = Field(
        8, ge=1, description="Rooms one user may own at once (POST /v1/rooms past it: 429; "
                             "admins exempt).")
    max_seats_per_room: int = Field(
        4, ge=1, le=16, description="Seats (avatars) in one room; a room asking more is 422.")
    max_participants_per_room: int = Field(
        64, ge=1, description="Performers + viewers in one room at once; past it a join gets "
                              "error 'busy', close code 4429.")
    max_invitations_per_room: int = Field(
        64, ge=1, description="Unexpired, unrevoked invitations of one room; past it POST "
                              ".../invitations is 429.")
    room_invitation_ttl_s: float = Field(
        86400.0, gt=0, description="Seconds an invitation stays valid unless it asks less.")
    room_invitation_max_ttl_s: float = Field(
        7 * 86400.0, gt=0, description="Longest ttl_s an invitation may ask (422 past it).")
    room_idle_timeout_s: float = Field(
        300.0, gt=0, description="Seconds a room with no participants lives on; then it is "
                                 "closed (the start-up room is pinned).")
    room_seat_hold_s: float = Field(
        10.0, ge=0, description="Seconds a seat whose performer left holds its last pose.")
    room_seat_ease_s: float = Field(
        2.0, ge=0, description="Seconds a held seat then takes to ease back to the rest pose.")
    startup_room: bool = Field(
        True, description="telesplat serve creates a room 'demo' (owner 'local', one seat of "
                          "the demo avatar, never closed for idleness) and prints its links; "
                          "the room is stored, so later starts reuse it (same id) and print "
                          "new links, the earlier ones staying valid.")
    restart_notice_s: float = Field(
        2.0, gt=0, le=30, description="On SIGTERM, seconds the server waits for each "
                                      "participant to be sent error 'restarting' and close "
                                      "1012 (clients then reconnect into the same room and "
                                      "seat) before uvicorn closes what is left.")
    job_backend: Literal["local", "ray"] = Field(
        "local", description="Where training jobs run. local: a worker process on this "
                             "machine; ray: a Ray task per job on the cluster at "
                             "cluster_address (docs/scale.md).")
    render_backend: Literal["local", "ray"] = Field(
        "local", description="Where sessions and rooms render. local: this process's render "
                             "threads; ray: render-worker actors on the cluster at "
                             "cluster_address, this server the gateway (docs/scale.md).")
    cluster_address: str | None = Field(
        None, description="Ray cluster address (host:port of the head), or 'auto': start a "
                          "private Ray on this machine. Needed when a backend is ray.")
    cluster_storage: Path | None = Field(
        None, description="Path every cluster node can reach (shared filesystem): job "
                          "datasets, checkpoints and finished packages. Default: data_dir "
                          "(one machine).")
    cluster_allow_no_auth: bool = Field(
        False, description="Let cluster_address 'auto' start a private Ray without token "
                           "auth (RAY_AUTH_MODE set to something else); refused otherwise, "
                           "since Ray listens on every interface and runs what it is sent.")
    cluster_object_store_bytes: int = Field(
        256 * 2**20, ge=78 * 2**20, description="Object store of the local Ray that "
                                                "cluster_address 'auto' starts, bytes.")
    ray_job_num_cpus: float | None = Field(
        None, gt=0, description="CPUs a training job asks the Ray cluster for (default: its "
                                "torch threads, 1).")
    ray_job_num_gpus: float | None = Field(
        None, ge=0, description="GPUs a training job asks the Ray cluster for (default: 1 "
                                "when the job's config device is cuda, else 0).")
    ray_job_max_concurrent: int = Field(
        16, ge=1, description="job_backend ray: training jobs running at once at most (each "
                              "also waits for the cluster to have room for its request).")
    render_actors: int = Field(2, ge=1, le=1024,
                               description="render_backend ray: render-worker actors started.")
    render_actor_num_cpus: float = Field(1.0, gt=0, description="CPUs per render-worker actor.")
    render_actor_num_gpus: float = Field(0.0, ge=0, description="GPUs per render-worker actor.")
    render_actor_restart_s: float = Field(
        10.0, gt=0, description="Seconds a dead render actor's rooms may take to be re-placed "
                                "before their participants get an error.")
    webrtc_ice_servers: list[str] = Field(
        default_factory=list, description="STUN/TURN server URLs WebRTC peers gather candidates "
                                          "with (e.g. stun:stun.example.org:3478); none by "
                                          "default: host candidates only (loopback, LAN).")
    webrtc_turn_username: str | None = Field(
        None, description="Username for the turn:/turns: servers of webrtc_ice_servers.")
    webrtc_turn_credential: str | None = Field(
        None, description="Credential (password) for the turn:/turns: servers of "
                          "webrtc_ice_servers.")
    webrtc_max_peers: int = Field(
        8, ge=0, description="WebRTC peers (WHEP viewers + WHIP publishers) at once; past it "
                             "POST .../whep or .../whip is 503 (0: WebRTC off).")
    webrtc_max_peers_per_user: int = Field(
        4, ge=1, description="WebRTC peers one token subject (or one invitation) may hold; "
                             "past it 429 (admins exempt).")
    webrtc_max_sdp_bytes: int = Field(
        32 * 1024, ge=1024, description="Largest SDP offer, bytes; past it 413, before any "
                                        "parsing.")
    webrtc_min_bitrate: int = Field(
        250_000, ge=10_000, description="Lowest target bit rate (bit/s) a WebRTC video encoder "
                                        "is set to, whatever the receiver's estimate (the "
                                        "delay-based estimate also falls when the machine, "
                                        "not the link, is slow).")
    webrtc_max_bitrate: int = Field(
        4_000_000, ge=10_000, description="Highest target bit rate (bit/s) of a WebRTC video "
                                          "encoder; the congestion estimate moves it within "
                                          "[webrtc_min_bitrate, webrtc_max_bitrate].")
    webrtc_connect_timeout_s: float = Field(
        15.0, gt=0, description="Seconds a WebRTC peer may take from its answer to a connected "
                                "ICE/DTLS transport; then it is closed and its slot freed.")
    webrtc_close_flush_s: float = Field(
        3.0, ge=0, le=10.0, description="Seconds a WebRTC peer closed for a too-large "
                                         "data-channel message waits for the client to "
                                         "acknowledge its too_large error before the "
                                         "association is aborted (3 s: room for one "
                                         "retransmission; aiortc's shortest is 1 s).")
    webrtc_max_message_bytes: int = Field(
        256 * 1024, ge=1024, description="Largest data-channel message, bytes: advertised as "
                                         "the SDP answer's a=max-message-size and enforced "
                                         "before reassembly; a peer sending a larger one is "
                                         "closed. At most limits.max_message_bytes.")
    webrtc_receive_window_bytes: int = Field(
        512 * 1024, ge=2048, description="Data-channel bytes a WebRTC peer may have waiting "
                                         "in reassembly (each chunk counted as at least "
                                         "1 KiB), advertised as its SCTP receive window; "
                                         "chunks past it are dropped unacknowledged (the "
                                         "sender retransmits). At least twice "
                                         "webrtc_max_message_bytes.")
    webrtc_max_inbound_bytes_per_s: float = Field(
        2**20, gt=0, description="Data-channel bytes per second one WebRTC peer may send, "
                                 "counted per SCTP chunk before reassembly (each at least "
                                 "1 KiB; burst max(one second, two webrtc_max_message_bytes)); "
                                 "past it chunks wait, unacknowledged, within "
                                 "webrtc_receive_window_bytes: the sender slows down.")
    webrtc_max_sctp_streams: int = Field(
        16, ge=1, description="SCTP stream ids (data channels) one WebRTC peer may use; "
                              "chunks on more are dropped.")
    webrtc_shared_encode: bool = Field(
        True, description="One video encode per picture for all the WebRTC viewers who see it "
                          "(server/webrtc/fanout.py); off: aiortc encodes for each viewer.")
    webrtc_keyframe_min_interval_s: float = Field(
        0.5, ge=0.0, le=10.0, description="With webrtc_shared_encode: the least time between "
                                          "keyframes asked of a shared video stream (a viewer "
                                          "joining or behind, a picture-loss request); what "
                                          "one viewer asks, all its viewers receive.")
    webrtc_sender_clock: Literal["capture", "send"] = Field(
        "capture", description="What a WebRTC viewer's RTP timestamps and RTCP sender reports "
                               "(video and voice) count: capture (the performer's capture "
                               "instants, one clock for both tracks: a browser lip-syncs "
                               "them) or send (aiortc's: the moment each was sent; "
                               "docs/benchmarks.md has both measured).")
    webrtc_max_sync_lag_s: float = Field(
        1.0, ge=0.05, le=10.0, description="With webrtc_sender_clock = capture: the most a "
                                           "viewer's picture is stamped behind its sending. A "
                                           "picture lagging more (a loaded server) is stamped "
                                           "as if captured this long before it left, so a "
                                           "browser holds the voice at most this long to "
                                           "lip-sync it (a jitter buffer asked to hold seconds "
                                           "plays silence).")
    voice_max_packet_bytes: int = Field(
        1276, ge=2, le=8192, description="Largest Opus packet a performer's voice may carry "
                                         "(bytes; 1276 is one largest Opus frame and its "
                                         "TOC byte); larger ones are dropped and counted.")
    voice_max_bitrate: int = Field(
        128_000, ge=6_000, description="Bits per second of Opus payload one seat's voice "
                                       "may send (token bucket, burst one second); packets "
                                       "past it are dropped and counted.")
    voice_max_delay_s: float = Field(
        0.0, ge=0.0, le=5.0, description="The longest a WebRTC listener's voice waits for "
                                         "its picture on the server (its delay buffer); 0: "
                                         "sent as it comes, the receiver syncs by the "
                                         "capture-clock sender reports (webrtc_sender_clock; "
                                         "docs/benchmarks.md, voice, has both measured).")
    voice_pacing: Literal["even", "frames"] = Field(
        "frames", description="How a WebRTC listener's voice waits for the picture: frames "
                              "(each packet until the frame of its drive leaves: bursts) or "
                              "even (each packet at its own cadence, shifted by the smoothed "
                              "picture lag; docs/benchmarks.md has both measured).")
    voice_buffer_packets: int = Field(
        64, ge=4, le=4096, description="Opus packets one listener may have waiting; past it "
                                       "the oldest is dropped and counted.")
    voice_speaking_dbov: float = Field(
        -50.0, ge=-127.0, le=0.0, description="A seat speaks while its packets' audio level "
                                              "(RFC 6464 dBov, as the sender measured it) "
                                              "is at least this; packets without a level "
                                              "count as speech.")
    voice_mix_max_seats: int = Field(
        4, ge=1, le=16, description="Most seats one room's mixed voice (a viewer's "
                                    "?voice=mix / hello.voice_mix) sums at once: the first "
                                    "to speak; another seat's packets are dropped and "
                                    "counted (unmixed) until one falls silent for 1 s.")
    voice_mix_bitrate: int = Field(
        48_000, ge=6_000, le=510_000, description="Bits per second the room's mixed voice is "
                                                  "encoded at (Opus, 20 ms frames).")
    loop_lag_interval_s: float = Field(
        0.05, ge=0.01, le=5.0, description="How often the event loop's lag is sampled (a "
                                           "short sleep; telesplat_event_loop_lag_ms).")
    loop_stall_log_ms: float = Field(
        0.0, ge=0.0, le=60_000.0, description="Log the event loop's stack when it is held "
                                              "this long (ms); 0: off. A diagnostic: one "
                                              "sleeping thread.")
    gc_freeze: bool = Field(
        True, description="Move what is alive once the server has started (the libraries, "
                          "the avatars, the warm-up's kernels) out of the garbage collector's "
                          "reach (gc.freeze), so a full collection walks only what came after: "
                          "a full collection holds every thread, the event loop's too.")
    voice_presence_interval_s: float = Field(
        0.25, ge=0.05, le=10.0, description="Shortest time between two presence updates a "
                                            "room sends because who speaks changed.")
    gaussian_ranges: GaussianRanges = Field(
        default_factory=GaussianRanges,
        description="Allowed values of an avatar's Gaussians (count, log-scales, local means, "
                    "opacity logits, SH, quaternion norms, and at the rest pose each splat's "
                    "3-sigma radius over the body's bounding-box diagonal, "
                    "max_splat_body_ratio), checked on upload (422) and when a stored avatar "
                    "is opened; a [gaussian_ranges] table or JSON in "
                    "TELESPLAT_GAUSSIAN_RANGES.")

    @field_validator("body_models", mode="before")
    @classmethod
    def _no_folder(cls, value: Any) -> Any:
        return None if value == "" else value  # an empty variable means "not given"

    @field_validator("demo_build_recipe", mode="before")
    @classmethod
    def _recipe_json(cls, value: Any) -> Any:
        """TELESPLAT_DEMO_BUILD_RECIPE is JSON."""
        if isinstance(value, str):
            return json.loads(value) if value.strip() else None
        return value

    @field_validator("demo_avatar")
    @classmethod
    def _demo(cls, value: str) -> str:
        if not value:
            raise ValueError("demo_avatar is synthetic, trained, none or a package path")
        return value

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _cors_list(cls, value: Any) -> Any:
        """TELESPLAT_CORS_ORIGINS: a JSON list, or comma-separated."""
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                try:
                    return json.loads(text)
                except ValueError as exc:
                    raise ValueError(f"cors_origins: not a JSON list: {exc}") from None
            return [origin.strip() for origin in text.split(",") if origin.strip()]
        return value

    @field_validator("cors_origins")
    @classmethod
    def _cors_origins(cls, value: list[str]) -> list[str]:
        if "*" in value:
            if len(value) > 1:
                raise ValueError("cors_origins: '*' (any origin) cannot be combined with other "
                                 f"origins, got {value}; give '*' alone or only origins")
            return value
        return list(dict.fromkeys(cors_origin(origin) for origin in value))

    @field_validator("webrtc_ice_servers", mode="before")
    @classmethod
    def _ice_list(cls, value: Any) -> Any:
        """TELESPLAT_WEBRTC_ICE_SERVERS is a comma-separated list."""
        if isinstance(value, str):
            return [url.strip() for url in value.split(",") if url.strip()]
        return value

    @field_validator("webrtc_ice_servers")
    @classmethod
    def _ice_urls(cls, value: list[str]) -> list[str]:
        bad = [url for url in value if not url.startswith(("stun:", "stuns:", "turn:", "turns:"))]
        if bad:
            raise ValueError(f"ICE server URLs start with stun:, stuns:, turn: or turns:, not "
                             f"{bad}")
        return value

    @model_validator(mode="after")
    def _bitrates(self) -> Settings:
        if self.webrtc_min_bitrate > self.webrtc_max_bitrate:
            raise ValueError(f"webrtc_min_bitrate {self.webrtc_min_bitrate} exceeds "
                             f"webrtc_max_bitrate {self.webrtc_max_bitrate}")
        return self

    @model_validator(mode="after")
    def _data_channel(self) -> Settings:
        if self.webrtc_max_message_bytes > self.limits.max_message_bytes:
            raise ValueError(f"webrtc_max_message_bytes {self.webrtc_max_message_bytes} "
                             f"exceeds limits.max_message_bytes "
                             f"{self.limits.max_message_bytes}")
        if self.webrtc_receive_window_bytes < 2 * self.webrtc_max_message_bytes:
            raise ValueError(f"webrtc_receive_window_bytes {self.webrtc_receive_window_bytes} "
                             f"is less than twice webrtc_max_message_bytes "
                             f"{self.webrtc_max_message_bytes} (a largest message, in "
                             "fragments of 512 bytes or more, must fit)")
        return self

    @model_validator(mode="after")
    def _frame_rate(self) -> Settings:
        if self.default_max_fps < self.limits.min_fps:
            raise ValueError(f"default_max_fps {self.default_max_fps} is below "
                             f"limits.min_fps {self.limits.min_fps}")
        return self

    @model_validator(mode="after")
    def _cluster(self) -> Settings:
        if "ray" in (self.job_backend, self.render_backend) and not self.cluster_address:
            raise ValueError("job_backend / render_backend 'ray' needs cluster_address "
                             "(host:port of a Ray head, or 'auto')")
        return self

    def render_pool(self) -> RenderThreads:
        """Render threads x threads per frame: the settings, or chosen from the usable cores
        (``TELESPLAT_THREADS`` overrides the machine's count)."""
        cores = machine_threads() if os.environ.get(THREADS_VAR, "").strip() else usable_cores()
        return render_threads(cores, self.render_threads, self.torch_threads)

    @property
    def cluster_storage_dir(self) -> Path:
        return self.cluster_storage or self.data_dir

    @property
    def tokens_path(self) -> Path:
        return self.tokens_file or self.data_dir / "tokens.json"

    @property
    def local_token_path(self) -> Path:
        """auth = "local": the local admin token, in plain text (0600)."""
        return self.data_dir / "local_token"

    @property
    def avatars_dir(self) -> Path:
        return self.data_dir / "avatars"


def _read_file(path: Path) -> dict[str, Any]:
    text = path.read_text()
    if path.suffix == ".json":
        data = json.loads(text)
    else:  # TOML by default
        data = tomllib.loads(text)
    if not isinstance(data, dict):
        raise ValueError(f"{path}: settings must be a table / object")
    # A [server] table is accepted too, so one file can hold other sections.
    return dict(data.get("server", data))


def _from_env(environ: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in Settings.model_fields:
        raw = environ.get(ENV_PREFIX + name.upper())
        if raw is None:
            continue
        out[name] = json.loads(raw) if name in NESTED else raw
    return out


def load_settings(path: str | Path | None = None, *, environ: dict[str, str] | None = None,
                  **overrides: Any) -> Settings:
    """Settings from defaults < file (``path``) < env vars < keyword overrides."""
    data: dict[str, Any] = _read_file(Path(path)) if path is not None else {}
    env = _from_env(dict(os.environ if environ is None else environ))
    for name in NESTED & env.keys():  # merged over the file's table, field by field
        env[name] = {**data.get(name, {}), **env[name]}
    data.update(env)
    data.update({k: v for k, v in overrides.items() if v is not None})
    return Settings.model_validate(data)
