"""The live rest pose and the default framing, over a real server: a new session shows the
relaxed stance (not the T-pose) with both hands inside the frame its welcome's framing gives,
the hand curls a page's sliders send change the hands' pixels there, ``reset`` comes back to
it, and a room seat whose performer left eases to it."""

import asyncio

import cv2
import numpy as np
import pytest
import torch

from avatar_core.body.rest_pose import REST_ARMS, rest_body_pose
from avatar_core.body.skeleton import JOINT
from avatar_core.render.camera_path import framing_target
from avatar_core.render.framing import fit_distance, frame_scene, head_box
from protocol import Drive, Orbit, Request, View, encode
from server.rooms.live import _toward_rest
from server.stream.drive import REST_BODY_POSE, DriveState, rest_value
from server.stream.scene import view_camera
from tests.server_fixtures import (
    is_type,
    recv_until,
    server_fixture,  # noqa: F401 (the `server` fixture)
    stream,
)

SIZE = 256
HANDS = ("left_wrist", "right_wrist", "left_middle3", "right_middle3", "left_thumb3",
         "right_thumb3")


def hand_curl(curl: float, sign: float) -> np.ndarray:
    """What the page's "left/right hand curl" slider sends (client/web/controls.js)."""
    pose = np.zeros((15, 3), np.float32)
    pose[:12, 2] = sign * curl
    pose[12:, 2] = sign * curl * 0.5
    return pose


def decode(frame) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR).astype(int)


def framing_view(framing) -> View:
    return View(orbit=Orbit(target=framing.target, distance=framing.distance,
                            fov_y_deg=framing.fov_y_deg))


def rest_joints(server) -> np.ndarray:
    """[J, 3] joints of the demo avatar as a new session poses it (no drive yet)."""
    animator = server.ctx.registry.open("demo").animator
    params = DriveState().smplx_params(animator.body_model, {})
    params["betas"] = animator.betas
    with torch.no_grad():
        return animator.body_model(params).joints[0].numpy()


def project(camera, points: np.ndarray) -> np.ndarray:
    cam = points @ camera.R.T + camera.t
    uv = cam @ camera.K.T
    return uv[:, :2] / uv[:, 2:]


def test_rest_is_the_relaxed_stance_not_the_t_pose(server):
    joints = rest_joints(server)
    shoulder, wrist = joints[JOINT["left_shoulder"]], joints[JOINT["left_wrist"]]
    assert wrist[1] < shoulder[1] - 0.25  # arms down, not out
    assert wrist[2] > 0.1 and abs(wrist[0]) < 0.25  # in front of the body, near the midline
    assert np.allclose(joints[JOINT["right_wrist"]] * [-1, 1, 1], wrist, atol=1e-4)  # mirrored
    pelvis = joints[JOINT["pelvis"]]
    assert pelvis[1] - 0.05 < wrist[1] < joints[JOINT["spine2"]][1]  # hips to belly height


def test_new_session_frames_both_hands_by_default(server):
    async def run():
        async with stream(server) as ws:
            framing = ws.welcome.framing
            assert framing is not None and framing.min_distance < framing.distance
            await ws.send(encode(Request(width=SIZE, height=SIZE)))
            await ws.send(encode(framing_view(framing)))
            frame = await recv_until(ws, lambda m: m.type == "frame" and m.width == SIZE)
            return framing, frame
    framing, frame = asyncio.run(run())
    assert frame.seq == -1  # nothing driven: the rest pose
    joints = rest_joints(server)
    chest = framing_target(server.ctx.registry.open("demo").animator.body_model.joint_template)
    camera = view_camera(framing_view(framing), SIZE, SIZE, chest)
    hands = project(camera, joints[[JOINT[n] for n in HANDS]])
    assert ((hands > 4) & (hands < SIZE - 4)).all(), hands
    head = project(camera, joints[[JOINT["head"]]])[0]
    assert 0 < head[1] < SIZE / 2  # the head is in the upper half, inside
    # The picture agrees: each hand's neighbourhood is the avatar, not the background.
    img = decode(frame)
    background = img[0, 0]
    for u, v in hands[:2].round().astype(int):
        patch = img[max(0, v - 3):v + 4, max(0, u - 3):u + 4]
        assert np.abs(patch - background).sum(-1).max() > 60, (u, v)
    # The server's own default orbit (no target, 2.7 m) shows both hands too.
    default = view_camera(View(orbit=Orbit()), SIZE, SIZE, chest)
    assert ((project(default, joints[[JOINT[n] for n in HANDS]]) > 0)
            & (project(default, joints[[JOINT[n] for n in HANDS]]) < SIZE)).all()


def test_hand_sliders_change_the_hands_in_the_default_view_and_reset_comes_back(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Request(width=SIZE, height=SIZE, codec="png")))
            await ws.send(encode(framing_view(ws.welcome.framing)))
            rest = await recv_until(ws, lambda m: m.type == "frame" and m.width == SIZE
                                    and m.codec == "png")
            frames = {}
            for seq, (side, sign) in enumerate((("left", -1.0), ("right", 1.0)), start=1):
                await ws.send(encode(Drive(seq=seq, smplx={f"{side}_hand_pose":
                                                           hand_curl(1.5, sign)})))
                frames[side] = await recv_until(ws, is_type("frame", seq=seq))
            await ws.send(encode(Drive(seq=9, reset=True)))
            back = await recv_until(ws, is_type("frame", seq=9))
            return ws.welcome.framing, rest, frames, back
    framing, rest, frames, back = asyncio.run(run())
    joints = rest_joints(server)
    chest = framing_target(server.ctx.registry.open("demo").animator.body_model.joint_template)
    camera = view_camera(framing_view(framing), SIZE, SIZE, chest)
    before = decode(rest)
    left = np.abs(decode(frames["left"]) - before).sum(-1)
    both = np.abs(decode(frames["right"]) - before).sum(-1)
    for side, diff in (("left", left), ("right", both)):
        u, v = project(camera, joints[[JOINT[f"{side}_middle1"]]])[0].round().astype(int)
        near = diff[max(0, v - 20):v + 21, max(0, u - 20):u + 21]
        assert (near > 60).sum() > 20, f"the {side} hand curl changed {(near > 60).sum()} px"
    # Only the left hand moved with the left slider: the right hand's neighbourhood is as it was.
    u, v = project(camera, joints[[JOINT["right_middle1"]]])[0].round().astype(int)
    assert (left[max(0, v - 20):v + 21, max(0, u - 20):u + 21] > 60).sum() == 0
    assert np.abs(decode(back) - before).max() == 0  # reset: exactly the rest frame again


def test_easing_goes_to_the_rest_pose_not_the_t_pose():
    held = np.zeros((21, 3), np.float32)
    assert np.allclose(_toward_rest("smplx", "body_pose", held, 0.0), REST_BODY_POSE)
    assert np.allclose(_toward_rest("smplx", "body_pose", held, 1.0), held)
    half = _toward_rest("smplx", "body_pose", held, 0.5)
    assert np.allclose(half, REST_BODY_POSE / 2)
    jaw = np.ones(3)
    assert np.allclose(_toward_rest("smplx", "jaw_pose", jaw, 0.25), 0.25)
    assert rest_value("flame", "expr", np.ones(5)).tolist() == [0.0] * 5
    assert np.allclose(rest_body_pose()[JOINT["left_elbow"] - 1], REST_ARMS["left_elbow"])


def test_framing_fits_boxes_and_keeps_the_head_whole():
    lo, hi = np.array([-0.3, 0.0, -0.1]), np.array([0.3, 0.8, 0.3])
    head = (np.array([-0.1, 0.5, -0.1]), np.array([0.1, 0.8, 0.1]))
    f = frame_scene([(lo, hi)], head)
    assert np.allclose(f.target, [0, 0.4, 0.1]) and np.allclose(f.face, [0, 0.65, 0])
    # the front face of the box (nearest, largest on screen) fits the frame with the margin
    tan = np.tan(np.radians(f.fov_y_deg) / 2)
    assert (f.distance - 0.2) * tan == pytest.approx(0.4 * 1.08)
    assert f.min_distance == pytest.approx(fit_distance(np.array([0.1, 0.15, 0.1]), 30, 0.25))
    with pytest.raises(ValueError, match="no box"):
        frame_scene([], head)
    with pytest.raises(ValueError, match="above the neck"):
        head_box(np.zeros((4, 3)), np.array([0, 1.0, 0]))


def test_room_framing_covers_every_placed_seat_and_faces_the_performed_one(server):
    from types import SimpleNamespace as Seat

    from server.stream.framing import room_framing

    animator = server.ctx.registry.open("demo").animator
    here = Seat(rotation=(0, 0, 0), translation=(0, 0, 0))
    there = Seat(rotation=(0, -0.4, 0), translation=(0.8, 0, 0))
    seats = [Seat(index=0, avatar="demo", placement=here),
             Seat(index=1, avatar="demo", placement=there)]
    solo = room_framing(seats[:1], 0, lambda _: animator)
    duet = room_framing(seats, 1, lambda _: animator)
    assert duet.target[0] == pytest.approx(0.4, abs=0.05)  # between the two
    assert duet.distance > solo.distance  # twice as wide: farther
    assert duet.face[0] == pytest.approx(solo.face[0] + 0.8, abs=0.02)  # seat 1's head
    assert room_framing(seats, 0, lambda _: animator).face == pytest.approx(solo.face)
    # every vertex of both seats at rest inside a square frame of the duet's framing
    params = DriveState().smplx_params(animator.body_model, {})
    params["betas"] = animator.betas
    with torch.no_grad():
        vertices = animator.body_model(params).vertices[0].numpy().astype(np.float64)
    rot = cv2.Rodrigues(np.asarray(there.rotation, np.float64))[0]
    both = np.concatenate([vertices, vertices @ rot.T + there.translation])
    camera = view_camera(framing_view(duet), SIZE, SIZE, np.zeros(3))
    uv = project(camera, both)
    assert ((uv >= 0) & (uv <= SIZE)).all(), (uv.min(0), uv.max(0))
