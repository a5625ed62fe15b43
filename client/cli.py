"""``telesplat-client``: stream a motion, manage avatars and training jobs from the shell.

    telesplat-client stream --avatar demo --motion smile.json --out frames/ [--fps 30]
    telesplat-client drive --avatar demo --webcam   (or --video clip.mp4)
    telesplat-client drive --room ID --seat 0 --webcam   (perform into a room)
    telesplat-client watch --room ID --out frames/ [--seconds 10] [--view 30,0,2.7]
    telesplat-client watch --webrtc --room ID --out frames/ [--codec h264]   (WHEP)
    telesplat-client rooms create --avatar demo   (then: rooms invite ID --scope watch)
    telesplat-client motions get smile --avatar demo --out smile.json
    telesplat-client jobs submit --dataset NAME [--config cfg.json] --watch
    telesplat-client jobs submit --video me.mp4 --watch   (enroll: an avatar of you)
    telesplat-client avatars list

``--server`` defaults to $TELESPLAT_SERVER (else http://127.0.0.1:8000), ``--token`` to
$TELESPLAT_TOKEN.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from protocol.cameras import CAMERA_NAMES
from protocol.jobs import MIN_USABLE_ITERATIONS, PRESET_NAMES

DEFAULT_SERVER = "http://127.0.0.1:8000"


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--server", default=os.environ.get("TELESPLAT_SERVER", DEFAULT_SERVER),
                        help="base URL (default $TELESPLAT_SERVER or %(default)s)")
    parser.add_argument("--token", default=os.environ.get("TELESPLAT_TOKEN"),
                        help="bearer token (default $TELESPLAT_TOKEN)")
    parser.add_argument("--json", action="store_true", help="print raw JSON answers")


def _rest(args: argparse.Namespace):
    from .rest import RestClient

    return RestClient(args.server, args.token)


TIME_COLUMNS = ("created", "started", "finished", "expires_at", "created_at", "updated_at")


def _cell(column: str, value: Any) -> str:
    """One table cell: epoch seconds as local date and time, progress as a percentage."""
    if value is None:
        return ""
    if column in TIME_COLUMNS and isinstance(value, int | float):
        return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(value))
    if column == "progress" and isinstance(value, int | float):
        return f"{100.0 * value:.0f}%"
    return str(value)


def _print(args: argparse.Namespace, value: Any, columns: tuple[str, ...] = ()) -> None:
    if args.json or not columns or not isinstance(value, list):
        print(json.dumps(value, indent=2, default=str))
        return
    rows = [[_cell(c, item.get(c)) for c in columns] for item in value]
    widths = [max([len(c), *(len(r[i]) for r in rows)]) for i, c in enumerate(columns)]
    for row in [list(columns), *rows]:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())


# -- stream ------------------------------------------------------------------------------


def server_motion(server: str, token: str | None, name: str, avatar: str,
                  fps: float | None = None):
    """The server's built-in clip ``name`` rigged for ``avatar``, as a Motion; ValueError
    listing the server's clips for a name it does not know."""
    from .motion_file import motion_from_json
    from .rest import ApiError, RestClient

    with RestClient(server, token) as api:
        known = [m.get("name") for m in api.motions()]
        if name not in known:
            raise ValueError(f"motion {name!r} is neither a .json / .npz file nor a built-in "
                             f"clip; built-in clips: {', '.join(known)}")
        try:
            data = api.motion(name, avatar=avatar, fps=fps)
        except ApiError as exc:
            raise ValueError(f"motion {name!r}: {exc}") from None
    return motion_from_json(data, f"built-in clip {name}")


async def stream_motion(server: str, token: str | None, avatar: str, motion_path: Path | str,
                        out: Path, *, fps: float | None = None, size: int = 512,
                        timeout: float = 30.0, progress: bool = True) -> list[Path]:
    """Drive ``avatar`` with a motion file (or a built-in clip of the server, by name) frame
    by frame; save each returned frame in ``out``.

    Lock-step: the next frame is driven once the previous one came back (and not before its
    time at ``fps``), so every motion frame gets its own image and none are coalesced.
    """
    from tqdm import tqdm

    from .images import save_frame
    from .motion_file import is_motion_file, load_motion
    from .stream import StreamClient

    if is_motion_file(motion_path):
        motion = load_motion(motion_path)
    else:  # a built-in clip: the server rigs it for the avatar
        motion = await asyncio.to_thread(server_motion, server, token, str(motion_path),
                                         avatar, fps)
    rate = fps or motion.fps or 30.0
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    async with await StreamClient.connect(server, avatar, token, timeout=timeout,
                                          client_name="telesplat-client") as client:
        await client.request(width=size, height=size,
                             max_fps=min(max(rate, 1.0), client.limits.max_fps))
        start = time.monotonic()
        with tqdm(total=len(motion), unit="frame", disable=not progress,
                  desc=f"streaming {Path(motion_path).name}") as bar:
            for i, params in enumerate(motion.frames):
                delay = start + i / rate - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                seq = await client.drive(**params, reset=i == 0)
                frame = await client.wait_frame(seq, timeout=timeout)
                written.append(save_frame(frame, out / f"{i:05d}"))
                bar.update(1)
    return written


def _backoff(args: argparse.Namespace):
    """--reconnect N: rejoin by itself, at most N tries in a row (0: never)."""
    from .stream import Backoff

    return Backoff(attempts=args.reconnect) if args.reconnect > 0 else None


def _reconnect_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reconnect", type=int, default=10, metavar="TRIES",
                        help="after a server restart or a dropped connection, rejoin the same "
                             "room and seat by itself: waits of 0.25 s doubling to 4 s "
                             "(jittered), at most TRIES tries in a row (default %(default)s; "
                             "0: end instead); a deleted room ends it at once")


def cmd_stream(args: argparse.Namespace) -> int:
    written = asyncio.run(stream_motion(args.server, args.token, args.avatar, args.motion,
                                        args.out, fps=args.fps, size=args.size,
                                        timeout=args.timeout, progress=not args.quiet))
    print(f"wrote {len(written)} frames to {args.out}")
    return 0


def cmd_drive(args: argparse.Namespace) -> int:
    from .remote_tracker import drive_from_camera

    if (args.avatar is None) == (args.room is None):
        print("telesplat-client: error: give --avatar or --room", file=sys.stderr)
        return 2
    if args.seat is not None and args.room is None:
        print("telesplat-client: error: --seat needs --room", file=sys.stderr)
        return 2
    source = args.webcam if args.webcam is not None else str(args.video)
    try:
        stats = asyncio.run(drive_from_camera(
            args.server, args.token, args.avatar, source, room=args.room, seat=args.seat,
            max_frames=args.frames,
            fov_x_deg=args.fov, out=args.out, timeout=args.timeout, progress=not args.quiet,
            body_models=args.body_models, reconnect=_backoff(args)))
    except (OSError, RuntimeError, ValueError) as exc:
        print(f"telesplat-client: error: {exc}", file=sys.stderr)
        return 2
    print(f"sent {stats['sent']} drives (tracking {stats['track_ms']:.0f} ms per frame)")
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
    from .watch import parse_view, watch_room

    view = parse_view(args.view) if args.view and args.view != "orbit" else None
    if args.voice and args.voice_mix:
        print("telesplat-client: error: --voice and --voice-mix are alternatives",
              file=sys.stderr)
        return 2
    if args.webrtc and (args.voice or args.voice_mix):
        print("telesplat-client: error: --voice records the WebSocket's voice messages; it "
              "does not combine with --webrtc (a WHEP viewer gets the voices as audio tracks)",
              file=sys.stderr)
        return 2
    if args.webrtc:
        from .watch import watch_room_webrtc

        result = asyncio.run(watch_room_webrtc(
            args.server, args.token, args.room, args.out, seconds=args.seconds,
            max_frames=args.frames, view=view, size=args.size, timeout=args.timeout,
            codec=args.codec, stamp=args.stamp))
        print(f"wrote {result['frames']} WebRTC ({result['codec']}) frames of room "
              f"{args.room} to {args.out}")
        return 0
    result = asyncio.run(watch_room(args.server, args.token, args.room, args.out,
                                    seconds=args.seconds, max_frames=args.frames, view=view,
                                    size=args.size, timeout=args.timeout,
                                    reconnect=_backoff(args),
                                    voice="mix" if args.voice_mix else args.voice))
    down = ", ".join(f"{r['downtime_s']:.1f}" for r in result["reconnections"])
    again = f" (reconnected after {down} s)" if down else ""
    heard = (f" and {result['voice_packets']} voice packets ({', '.join(result['voice_files'])})"
             if args.voice or args.voice_mix else "")
    print(f"wrote {result['frames']} frames{heard} of room {args.room} to {args.out}{again}")
    return 0


# -- rooms -------------------------------------------------------------------------------


def cmd_rooms(args: argparse.Namespace) -> int:
    with _rest(args) as api:
        if args.action == "list":
            _print(args, api.rooms(), ("id", "name", "owner", "viewers"))
        elif args.action == "get":
            _print(args, api.room(args.id))
        elif args.action == "create":
            seats = [{"avatar": avatar} for avatar in args.avatar] if args.avatar else None
            room = api.create_room(seats, name=args.name)
            if args.json:
                _print(args, room)
            else:  # the id, for 'rooms invite ID' (--json: the whole room)
                print(room["id"])
        elif args.action == "delete":
            api.delete_room(args.id)
            print(f"deleted room {args.id}")
        elif args.action == "invite":
            invitation = api.invite(args.id, args.scope, seat=args.seat, ttl_s=args.ttl)
            if args.json:
                _print(args, invitation)
            else:  # the token is shown once: in the link
                print(api.link(invitation["link"]))
        elif args.action == "invitations":
            _print(args, api.invitations(args.id), ("id", "scope", "seat", "expires_at"))
        elif args.action == "revoke":
            api.revoke_invitation(args.id, args.invitation)
            print(f"revoked invitation {args.invitation}")
    return 0


# -- avatars -----------------------------------------------------------------------------


def cmd_avatars(args: argparse.Namespace) -> int:
    with _rest(args) as api:
        if args.action == "list":
            _print(args, api.avatars(), ("id", "name", "owner", "num_gaussians"))
        elif args.action == "get":
            _print(args, api.avatar(args.id))
        elif args.action == "upload":
            _print(args, api.upload_avatar(args.package, name=args.name))
        elif args.action == "download":
            print(api.download_avatar(args.id, args.out))
        elif args.action == "delete":
            api.delete_avatar(args.id)
            print(f"deleted {args.id}")
    return 0


# -- motions -----------------------------------------------------------------------------


def cmd_motions(args: argparse.Namespace) -> int:
    with _rest(args) as api:
        if args.action == "list":
            _print(args, api.motions(), ("name", "category", "duration"))
            return 0
        motion = api.motion(args.name, avatar=args.avatar, fps=args.fps)
        if args.out:
            Path(args.out).write_text(json.dumps(motion))
            print(f"wrote {len(motion.get('frames', []))} frames to {args.out}")
        else:
            print(json.dumps(motion))
    return 0


# -- jobs --------------------------------------------------------------------------------




def _config(value: str | None) -> dict[str, Any] | str | None:
    """--config: a JSON file (a training config) or a preset name (protocol.jobs.PRESET_NAMES:
    default, quick, demo, test, enroll)."""
    if value is None:
        return None
    path = Path(value)
    if path.suffix == ".json" or path.is_file():
        return json.loads(path.read_text())
    return value


def watch_job(api, job_id: str, *, progress: bool = True) -> dict[str, Any]:
    """Follow a job's events with a progress bar until it ends; returns its final status.
    The bar reads each event's ``progress`` (protocol.jobs, the one job-event schema)."""
    from tqdm import tqdm

    from protocol.jobs import TERMINAL_JOB_STATES, progress_of

    with tqdm(total=100, unit="%", disable=not progress, desc=f"job {job_id}",
              bar_format="{l_bar}{bar}| {postfix}") as bar:
        # The server ends the stream with an `end` event once the job has finished; a stream
        # that times out first (no news for 10 minutes) is resumed after the last event id.
        last_id = None
        for _ in range(1000):  # reconnects, each after a bounded stream
            for event in api.job_events(job_id, after=last_id):
                last_id = int(event.id) if event.id and event.id.isdigit() else last_id
                data = event.data if isinstance(event.data, dict) else {}
                fraction = progress_of(event.event, data)
                if fraction is not None:
                    bar.update(round(fraction * 100) - bar.n)
                state = data.get("state")
                loss = f" loss {data['loss']:.4f}" if isinstance(data.get("loss"), float) else ""
                what = state or data.get("stage") or event.event  # an enrollment's stage
                bar.set_postfix_str(f"{what}{loss}", refresh=True)
                if event.event == "end":
                    return api.job(job_id)
            if api.job(job_id).get("state") in TERMINAL_JOB_STATES:
                break
    return api.job(job_id)


def job_summary(job: dict[str, Any]) -> str:
    """A few lines on how a job ended (``--json`` prints the whole status instead)."""
    state = job.get("state")
    took = ""
    if isinstance(job.get("started"), int | float) and isinstance(job.get("finished"),
                                                                   int | float):
        took = f" in {job['finished'] - job['started']:.0f} s"
    if job.get("kind") == "enroll":
        head = f"enrollment job {job.get('id')} {state}{took}"
    else:
        head = f"job {job.get('id')} {state}{took}: {job.get('iteration')}/{job.get('total')} " \
               "iterations"
    if isinstance(job.get("loss"), int | float):
        head += f", loss {job['loss']:.4f}"
    lines = [head]
    if job.get("avatar_id"):
        lines.append(f"avatar {job['avatar_id']}")
    if job.get("error"):
        lines.append(f"error: {job['error']}")
    return "\n".join(lines)


def _warn_small(job: dict[str, Any]) -> None:
    from protocol.jobs import small_job_warning

    total = job.get("total")  # (an enrollment's total counts thousandths, not iterations)
    enroll = job.get("kind") == "enroll"
    warning = small_job_warning(total) if isinstance(total, int) and not enroll else None
    if warning:
        print(f"telesplat-client: {warning}", file=sys.stderr)


def cmd_jobs(args: argparse.Namespace) -> int:
    with _rest(args) as api:
        if args.action == "submit":
            config = _config(args.config)
            job = api.submit_job(dataset=args.dataset, archive=args.archive, video=args.video,
                                 config=config, name=args.name)
            job_id = job.get("id") or job.get("job_id")
            print(f"submitted job {job_id}")
            _warn_small(job)
            if args.watch:
                final = watch_job(api, job_id, progress=not args.quiet)
                print(json.dumps(final, indent=2) if args.json else job_summary(final))
                return 0 if final.get("state") == "succeeded" else 1
        elif args.action == "list":
            _print(args, api.jobs(), ("id", "name", "state", "progress", "created"))
        elif args.action == "status":
            _print(args, api.job(args.id))
        elif args.action == "watch":
            final = watch_job(api, args.id, progress=not args.quiet)
            print(json.dumps(final, indent=2) if args.json else job_summary(final))
            return 0 if final.get("state") == "succeeded" else 1
        elif args.action == "logs":
            print(api.job_logs(args.id, tail=args.tail))
        elif args.action == "cancel":
            _print(args, api.cancel_job(args.id))
        elif args.action == "result":
            _print(args, api.job_result(args.id))
    return 0


def cmd_health(args: argparse.Namespace) -> int:
    with _rest(args) as api:
        _print(args, api.health())
    return 0


# -- parser ------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="telesplat-client", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("stream", help="stream a motion file and save the frames")
    _common(p)
    p.add_argument("--avatar", required=True)
    p.add_argument("--motion", required=True,
                   help="a built-in clip by name (smile, talk_calm, ...: 'motions list') or "
                        "a .json list of per-frame dicts or .npz with a frame axis")
    p.add_argument("--out", type=Path, required=True, help="folder for the frames")
    p.add_argument("--fps", type=float, default=None,
                   help="drive rate (default: the file's, else 30)")
    p.add_argument("--size", type=int, default=512, help="frame width and height")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait per frame")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_stream)

    p = sub.add_parser("drive", help="track the webcam or a video here and drive an avatar "
                                     "with the fitted parameters (the remote tracker)")
    _common(p)
    p.add_argument("--avatar", help="drive a private session on this avatar")
    p.add_argument("--room", help="perform into this room instead (see 'rooms')")
    p.add_argument("--seat", type=int, default=None,
                   help="the room's seat to perform (default: the invitation's, else 0)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--webcam", type=int, nargs="?", const=0, metavar="INDEX",
                     help="camera index (default 0)")
    src.add_argument("--video", type=Path, help="video file")
    p.add_argument("--frames", type=int, default=None, help="at most this many frames")
    p.add_argument("--fov", type=float, default=60.0,
                   help="the camera's horizontal field of view, degrees")
    p.add_argument("--body-models", type=Path, default=None,
                   help="body-model folder to fit, official file names (the server's; "
                        "default: $TELESPLAT_BODY_MODELS, else the synthetic family)")
    p.add_argument("--out", type=Path, default=None, help="save the returned frames here")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait per frame")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _reconnect_argument(p)
    p.set_defaults(func=cmd_drive)

    p = sub.add_parser("watch", help="join a room as a viewer and save the frames it gets")
    _common(p)
    p.add_argument("--room", required=True)
    p.add_argument("--out", type=Path, required=True,
                   help="folder for the frames and frames.jsonl")
    p.add_argument("--seconds", type=float, default=10.0, help="record this long")
    p.add_argument("--frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--view", default=None, metavar="YAW,PITCH,DIST|NAME",
                   help="own viewpoint: degrees, degrees, metres, or a camera preset: "
                        f"{', '.join(CAMERA_NAMES)} (orbit: the room's camera)")
    p.add_argument("--size", type=int, default=512, help="frame width and height")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait per frame")
    p.add_argument("--webrtc", action="store_true",
                   help="watch over WebRTC (WHEP): save the decoded video frames as PNG")
    p.add_argument("--codec", choices=("vp8", "h264"), default=None,
                   help="--webrtc: the codec to prefer in the offer (default: aiortc's, VP8)")
    p.add_argument("--stamp", action="store_true",
                   help="--webrtc: ask for frame stamps and record each frame's drive seq")
    p.add_argument("--voice", action="store_true",
                   help="also record the seats' voices: voice-seat{N}.wav and voice.jsonl "
                        "(capture times, to match frames.jsonl)")
    p.add_argument("--voice-mix", action="store_true",
                   help="record the room's one mixed voice instead (decoded, summed and "
                        "encoded once on the server): voice-mix.wav and voice.jsonl")
    _reconnect_argument(p)
    p.set_defaults(func=cmd_watch)

    p = sub.add_parser("rooms", help="live rooms: one performer per seat, viewers watch")
    rooms = p.add_subparsers(dest="action", required=True)
    _common(rooms.add_parser("list"))
    for action in ("get", "delete", "invitations"):
        r = rooms.add_parser(action)
        _common(r)
        r.add_argument("id")
    r = rooms.add_parser("create")
    _common(r)
    r.add_argument("--avatar", action="append", help="a seat's avatar (repeat for more seats)")
    r.add_argument("--name")
    r = rooms.add_parser("invite", help="print an invitation's page link (its token inside)")
    _common(r)
    r.add_argument("id")
    r.add_argument("--scope", choices=("watch", "perform"), default="watch")
    r.add_argument("--seat", type=int, default=None, help="perform: the seat")
    r.add_argument("--ttl", type=float, default=None, help="seconds until it expires")
    r = rooms.add_parser("revoke")
    _common(r)
    r.add_argument("id")
    r.add_argument("invitation")
    p.set_defaults(func=cmd_rooms)

    p = sub.add_parser("avatars", help="list, upload, download, delete avatars")
    avatars = p.add_subparsers(dest="action", required=True)
    a = avatars.add_parser("list")
    _common(a)
    for action in ("get", "delete"):
        a = avatars.add_parser(action)
        _common(a)
        a.add_argument("id")
    a = avatars.add_parser("upload")
    _common(a)
    a.add_argument("package", type=Path, help="avatar package: .zip or folder")
    a.add_argument("--name")
    a = avatars.add_parser("download")
    _common(a)
    a.add_argument("id")
    a.add_argument("--out", type=Path, default=Path("."), help="file or folder")
    p.set_defaults(func=cmd_avatars)

    p = sub.add_parser("motions", help="the server's built-in motion clips")
    motions = p.add_subparsers(dest="action", required=True)
    _common(motions.add_parser("list"))
    m = motions.add_parser("get", help="per-frame parameters of a clip (JSON)")
    _common(m)
    m.add_argument("name")
    m.add_argument("--avatar")
    m.add_argument("--fps", type=float)
    m.add_argument("--out", type=Path, help="write the JSON here (streamable with 'stream')")
    p.set_defaults(func=cmd_motions)

    p = sub.add_parser("jobs", help="training jobs")
    jobs = p.add_subparsers(dest="action", required=True)
    j = jobs.add_parser("submit")
    _common(j)
    source = j.add_mutually_exclusive_group(required=True)
    source.add_argument("--dataset", help="a dataset name the server knows")
    source.add_argument("--archive", type=Path, help="a dataset archive to upload")
    source.add_argument("--video", type=Path,
                        help="enroll: one person turning slowly before a fixed camera, smiling "
                             "and opening their hands, 20-60 s (MP4, MOV, WebM); the job makes "
                             "an avatar of them (preset 'enroll')")
    j.add_argument("--config", help="training config: a JSON file or a preset name: "
                   f"{', '.join(PRESET_NAMES)} (test: a smoke run, no usable avatar; "
                   f"demo: the least that gives one, {MIN_USABLE_ITERATIONS} iterations); "
                   "with --video: 'enroll' (the default) or a JSON file of EnrollConfig "
                   "fields")
    j.add_argument("--name")
    j.add_argument("--watch", action="store_true", help="follow progress until it ends")
    j.add_argument("--quiet", action="store_true")
    _common(jobs.add_parser("list"))
    for action in ("status", "watch", "logs", "cancel", "result"):
        j = jobs.add_parser(action)
        _common(j)
        j.add_argument("id")
        j.add_argument("--quiet", action="store_true")
        if action == "logs":
            j.add_argument("--tail", type=int, help="only the last N lines")
    p.set_defaults(func=cmd_jobs)

    p = sub.add_parser("health", help="server health")
    _common(p)
    p.set_defaults(func=cmd_health)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .rest import ApiError
    from .stream import StreamError

    try:
        return args.func(args)
    except (ApiError, StreamError, ValueError, OSError, TimeoutError) as exc:
        print(f"telesplat-client: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
