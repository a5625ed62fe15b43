"""client/web/protocol.js: generated from the Python definitions and never drifting from them,
and interoperable with protocol.codec across the language boundary (node, else Chromium)."""

from __future__ import annotations

import base64
import functools
import json
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import msgpack
import numpy as np
import pytest

from protocol import (
    DEFAULT_LIMITS,
    PROTOCOL_VERSION,
    AvatarInfo,
    Error,
    Frame,
    Pong,
    ProtocolError,
    Request,
    Stats,
    Welcome,
    decode_client,
    encode,
)
from protocol.jsgen import OUTPUT, render
from tests.test_client_units import chromium_missing, make_chromium, node, run_node

WEB = Path(__file__).resolve().parent.parent / "client" / "web"


def test_committed_protocol_js_is_freshly_generated():
    assert OUTPUT == WEB / "protocol.js"
    assert OUTPUT.read_text(encoding="utf-8") == render(), \
        "client/web/protocol.js is stale: run python -m protocol.jsgen"
    assert render() == render()  # deterministic


def test_generated_constants_match_python():
    text = render()
    assert f"export const PROTOCOL_VERSION = Object.freeze({PROTOCOL_VERSION});" in text
    assert '"max_array_elements": 4096' in text and '"unsupported"' in text
    assert 'import { decode as unpackMsgpack, encode as packMsgpack } from ' \
           '"./vendor/msgpack/index.mjs";' in text
    assert (WEB / "vendor" / "msgpack" / "index.mjs").is_file()
    assert "ISC" in (WEB / "vendor" / "msgpack" / "LICENSE").read_text() or \
           "Permission to use" in (WEB / "vendor" / "msgpack" / "LICENSE").read_text()


# -- running JavaScript: node when installed, else headless Chromium ----------------------


class _Quiet(SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep pytest output clean
        pass

    def do_GET(self):  # noqa: N802 (http.server's naming)
        if self.path == "/blank.html":
            body = b"<!doctype html><title>js</title>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
            return
        super().do_GET()


@pytest.fixture(scope="module")
def run_js():
    """A function (js_body, input) -> output: `js_body` is the text of an async function
    (P, input) => JSON-able, where P is the protocol.js module."""
    if node():
        url = (WEB / "protocol.js").as_uri()

        def via_node(body: str, data) -> object:
            script = (f"import * as P from {json.dumps(url)};\n"
                      "import {readFileSync} from 'node:fs';\n"
                      "const input = JSON.parse(readFileSync(0, 'utf8'));\n"
                      f"const fn = {body};\n"
                      "console.log(JSON.stringify(await fn(P, input)));\n")
            return json.loads(run_node(script, json.dumps(data)))

        yield via_node
        return
    reason = chromium_missing()
    if reason:
        pytest.skip(f"neither node nor Chromium: {reason}")
    handler = functools.partial(_Quiet, directory=str(WEB))
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    driver = make_chromium()
    try:
        driver.get(f"http://127.0.0.1:{server.server_port}/blank.html")

        def via_chromium(body: str, data) -> object:
            script = ("const done = arguments[arguments.length - 1];"
                      f"const input = {json.dumps(data)};"
                      "import('/protocol.js').then(async (P) => {"
                      f"  const fn = {body};"
                      "  done(JSON.stringify(await fn(P, input)));"
                      "}).catch((e) => done(JSON.stringify({error: String(e)})));")
            return json.loads(driver.execute_async_script(script))

        yield via_chromium
    finally:
        driver.quit()
        server.shutdown()


B64 = """
  const b64 = (bytes) => btoa(Array.from(bytes, (b) => String.fromCharCode(b)).join(""));
  const unb64 = (s) => Uint8Array.from(atob(s), (c) => c.charCodeAt(0));
"""


def test_js_encoded_client_messages_decode_in_python(run_js):
    body = "async (P, input) => {" + B64 + """
      const messages = [
        {type: "hello", version: P.PROTOCOL_VERSION, client: "js", token: null},
        {type: "drive", seq: 7, reset: true,
         smplx: {jaw_pose: new Float32Array([0.1, 0.2, 0.3]),
                 body_pose: Array.from({length: 21}, (_, i) => [i / 8, 0, -i / 8]),
                 left_hand_pose: new Float32Array(45).fill(0.25),
                 expression: P.packArray(new Float64Array([1, -1]), [2])},
         flame: {expr: [0.5, 0.25]}, mano_right: {hand_pose: new Float32Array(6)}},
        {type: "view", orbit: {yaw_deg: 30.5, pitch_deg: -10, distance: 2}, moving: true},
        {type: "view", camera: {K: [[500, 0, 256], [0, 500, 256], [0, 0, 1]],
                                R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], t: [0, 0, 2.5],
                                width: 512, height: 512}},
        {type: "request", width: 384, height: 256, codec: "jpeg",
         background: new Float32Array([1, 1, 1]), outputs: ["rgb", "depth"], quality: 0.5},
        {type: "image", seq: 9007199254740991, format: "jpeg",
         data: new Uint8Array([255, 216, 1, 2])},
        {type: "ping", t: 1234.5},
      ];
      return messages.map((m) => ({errors: P.validate(m), bytes: b64(P.encode(m))}));
    }"""
    out = run_js(body, None)
    assert all(item["errors"] == [] for item in out), [item["errors"] for item in out]
    hello, drive, orbit, camera, request, image, ping = (
        decode_client(base64.b64decode(item["bytes"])) for item in out)
    assert hello.version == PROTOCOL_VERSION and hello.client == "js" and hello.token is None
    assert drive.seq == 7 and drive.reset
    np.testing.assert_allclose(drive.smplx["jaw_pose"], [0.1, 0.2, 0.3], rtol=1e-6)
    assert drive.smplx["body_pose"].shape == (21, 3) and drive.smplx["body_pose"][4, 2] == -0.5
    assert drive.smplx["left_hand_pose"].shape == (15, 3)
    assert (drive.smplx["left_hand_pose"] == 0.25).all()
    np.testing.assert_array_equal(drive.smplx["expression"], [1, -1])
    np.testing.assert_array_equal(drive.flame["expr"], [0.5, 0.25])
    assert drive.mano_right["hand_pose"].shape == (6,)  # PCA coefficients
    assert orbit.orbit.yaw_deg == 30.5 and orbit.moving and orbit.camera is None
    assert camera.camera.width == 512 and camera.camera.t == (0, 0, 2.5)
    assert request.width == 384 and request.background == (1, 1, 1)
    assert request.outputs == ["rgb", "depth"] and request.quality == 0.5
    assert image.seq == 2**53 - 1 and image.data == bytes([255, 216, 1, 2])
    assert ping.t == 1234.5


def _server_messages() -> list[bytes]:
    info = AvatarInfo(id="demo", name="Demo", num_gaussians=1000, sh_degree=3,
                      metadata={"expression_names": ["smile"]})
    return [
        encode(Welcome(session="s1", avatar=info, limits=DEFAULT_LIMITS, codecs=["jpeg", "png"],
                       request=Request(width=512, height=512, outputs=["rgb"]))),
        encode(Frame(seq=3, frame=10, codec="jpeg", width=4, height=2, data=b"\xff\xd8xyz",
                     timings={"pose": 1.5, "render": 20.0})),
        encode(Error(code="unsupported", message="no tracker", answers={"type": "image",
                                                                         "seq": 4})),
        encode(Stats(fps=29.5, frames=100, dropped=1, coalesced=2, bytes_per_s=1e6,
                     render_ms=12.5, sessions=1)),
        encode(Pong(t=99.25)),
        encode({"type": "drive", "seq": 1, "smplx": {"jaw_pose": np.array([1, 2, 3], "<f4"),
                                                      "body_pose": np.zeros((21, 3))}}),
    ]


def test_python_encoded_messages_decode_and_validate_in_js(run_js):
    body = "async (P, input) => {" + B64 + """
      return input.map((s) => {
        const m = P.decode(unb64(s));
        const out = {type: m.type, errors: P.validate(m)};
        if (m.type === "frame") out.data = Array.from(m.data);
        if (m.type === "welcome") out.limits = m.limits.max_fps;
        if (m.type === "error") out.answers = m.answers;
        if (m.type === "drive") {
          const jaw = P.unpackArray(m.smplx.jaw_pose);
          const body = P.unpackArray(m.smplx.body_pose);
          out.jaw = [Array.from(jaw.array), jaw.shape, m.smplx.jaw_pose.dtype];
          out.body = [body.array.length, body.shape, m.smplx.body_pose.dtype];
        }
        return out;
      });
    }"""
    out = run_js(body, [base64.b64encode(b).decode() for b in _server_messages()])
    assert [o["type"] for o in out] == ["welcome", "frame", "error", "stats", "pong", "drive"]
    assert all(o["errors"] == [] for o in out), [o["errors"] for o in out]
    assert out[0]["limits"] == 60
    assert bytes(out[1]["data"]) == b"\xff\xd8xyz"
    assert out[2]["answers"] == {"type": "image", "seq": 4}
    assert out[5]["jaw"] == [[1, 2, 3], [3], "<f4"]
    assert out[5]["body"] == [63, [21, 3], "<f8"]


def _nd(arr, dtype="<f4", data=None):
    arr = np.asarray(arr, dtype=dtype)
    return {"nd": True, "dtype": dtype, "shape": list(arr.shape),
            "data": arr.tobytes() if data is None else data}


# Messages both sides must reject (raw maps, packed without any validation).
BAD = [
    {"type": "drive", "seq": -1},
    {"type": "drive", "seq": 1, "color": 3},
    {"type": "drive", "seq": 1, "smplx": {"jaw_pose": [1.0, 2.0]}},
    {"type": "drive", "seq": 1, "smplx": {"body_pose": [0.0] * 62}},
    {"type": "drive", "seq": 1, "smplx": {"jaw": [0.0, 0.0, 0.0]}},
    {"type": "drive", "seq": 1, "smplx": {"jaw_pose": [0.0, float("nan"), 0.0]}},
    {"type": "drive", "seq": 1, "smplx": {"jaw_pose": _nd([0, 0, 0], "<f4", b"\0" * 8)}},
    {"type": "drive", "seq": 1, "smplx": {"jaw_pose": _nd([0, 0, 0], ">f4")}},
    {"type": "drive", "seq": 1, "flame": {"expr": [0.0] * 101}},
    {"type": "drive", "seq": 1, "mano_left": {"hand_pose": [0.0] * 46}},
    {"type": "drive", "seq": 1, "smplx": {"betas": [1e300]}},               # out of range
    {"type": "drive", "seq": 1, "smplx": {"leye_pose": _nd([1e38, 0, 0])}},
    {"type": "drive", "seq": 1, "flame": {"translation": [0, 0, 11]}},
    {"type": "drive", "seq": 1, "mano_right": {"hand_pose": [11.0] * 6}},
    {"type": "view"},
    {"type": "view", "orbit": {"yaw_deg": 0}, "camera": {
        "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "t": [0, 0, 0], "width": 4, "height": 4}},
    {"type": "view", "orbit": {"pitch_deg": 100}},
    {"type": "view", "orbit": {"distance": 0}},
    {"type": "view", "orbit": {"fov_y_deg": 1e-9}},
    {"type": "view", "orbit": {"target": [0, 1e200, 0]}},
    {"type": "request", "width": 5000},
    {"type": "request", "width": 8},
    {"type": "request", "background": [2, 0, 0]},
    {"type": "request", "codec": "gif"},
    {"type": "request", "outputs": []},
    {"type": "request", "max_fps": 500},
    {"type": "request", "max_fps": 0.001},
    {"type": "image", "seq": 1, "data": b""},
    {"type": "image", "seq": 1, "format": "bmp", "data": b"x"},
    {"type": "hello", "token": "x" * 600},
    {"type": "ping", "t": "soon"},
    {"type": "teleport"},
]
GOOD = [
    {"type": "drive", "seq": 0},
    {"type": "drive", "seq": 1, "smplx": {"right_hand_pose": [0.0] * 12, "betas": [1.0]}},
    {"type": "view", "orbit": {}},
    {"type": "request"},
    {"type": "hello"},
]


def test_validate_in_js_agrees_with_python_on_good_and_bad_messages(run_js):
    for message in BAD:
        with pytest.raises(ProtocolError):
            decode_client(msgpack.packb(message, use_bin_type=True))
    for message in GOOD:
        decode_client(msgpack.packb(message, use_bin_type=True))
    body = "async (P, input) => {" + B64 + """
      return input.map((s) => P.validate(P.decode(unb64(s))));
    }"""
    packed = [base64.b64encode(msgpack.packb(m, use_bin_type=True)).decode()
              for m in BAD + GOOD]
    out = run_js(body, packed)
    for message, errors in zip(BAD, out[:len(BAD)], strict=True):
        assert errors, f"JS accepted a message Python rejects: {message}"
    for message, errors in zip(GOOD, out[len(BAD):], strict=True):
        assert errors == [], f"JS rejected a valid message {message}: {errors}"


def test_js_encode_with_validate_throws_protocol_error(run_js):
    body = """async (P) => {
      try { P.encode({type: "drive", seq: 1, smplx: {jaw_pose: [1]}}, {validate: true}); }
      catch (e) { return [e.name, e.code, e.message]; }
      return null;
    }"""
    name, code, message = run_js(body, None)
    assert (name, code) == ("ProtocolError", "invalid") and "jaw_pose" in message
