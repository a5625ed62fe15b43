"""Built-in clips and camera presets by name, wherever a motion or a camera is taken:
``telesplat render --motion smile --camera front`` and ``telesplat-client stream --motion
talk_calm`` / ``watch --view front``, run by their ``main`` in process; an unknown name is a
clear error that lists the names; ``--camera orbit`` of one frame is the front."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from avatar_core.cli import main as engine_main
from avatar_core.motion.library import ALIASES, MOTIONS, clip_names
from client.cli import main as client_main
from client.watch import parse_view
from protocol.cameras import CAMERA_PRESETS, orbit_yaws
from tests.cli_run import run_main
from tests.server_fixtures import server_fixture  # noqa: F401 (the `server` fixture)

pytest.importorskip("avatar_core.render.rasterize")


def _render(capsys, models: Path, out: Path, *args: str) -> list[np.ndarray]:
    done = run_main(engine_main, ["render", "synthetic", "--models", models, "--size", "32",
                                  "--out", out, *args], capsys)
    assert done.returncode == 0, done.stderr
    return [cv2.imread(str(p)) for p in sorted(out.glob("frame_*.png"))]


def test_clip_names_are_the_library_and_the_engine_clips():
    assert {"demo", "rest", "smile", "talk_calm", "talk"} <= set(clip_names())
    assert set(clip_names()) == {"demo", "rest", *MOTIONS, *ALIASES}
    assert orbit_yaws(1) == [0.0] and orbit_yaws(3) == [-60.0, 0.0, 60.0]


def test_render_takes_clip_and_camera_names(synthetic_files, tmp_path, capsys):
    models = synthetic_files.root
    smile = _render(capsys, models, tmp_path / "smile", "--motion", "smile", "--camera", "front",
                    "--frames", "2")
    assert len(smile) == 2 and smile[0].shape == (32, 32, 3)
    # one frame of the orbit is the front view, not the sweep's -60 degree side view
    orbit = _render(capsys, models, tmp_path / "orbit", "--motion", "rest", "--camera", "orbit",
                    "--frames", "1")
    front = _render(capsys, models, tmp_path / "front", "--motion", "rest", "--camera", "front",
                    "--frames", "1")
    left = _render(capsys, models, tmp_path / "left", "--motion", "rest", "--camera", "left",
                   "--frames", "1")
    assert np.array_equal(orbit[0], front[0])
    assert np.abs(left[0].astype(int) - front[0]).mean() > 1.0


def test_render_unknown_names_list_the_known_ones(synthetic_files, tmp_path, capsys):
    done = run_main(engine_main, ["render", "synthetic", "--models", synthetic_files.root,
                                  "--motion", "smiel", "--out", tmp_path / "x"], capsys)
    assert done.returncode == 2
    assert "'smiel'" in done.stderr and "smile" in done.stderr and "talk_calm" in done.stderr
    done = run_main(engine_main, ["render", "synthetic", "--models", synthetic_files.root,
                                  "--camera", "back", "--out", tmp_path / "y"], capsys)
    assert done.returncode == 2
    assert "'back'" in done.stderr and "front, orbit, left, right" in done.stderr


def test_watch_view_takes_preset_names():
    assert parse_view("front") == CAMERA_PRESETS["front"]
    assert parse_view("30,0,2.7") == {"yaw_deg": 30.0, "pitch_deg": 0.0, "distance": 2.7}
    with pytest.raises(ValueError, match="front, orbit, left, right"):
        parse_view("back")


def test_client_stream_takes_a_builtin_clip_by_name(server, tmp_path, capsys):  # noqa: F811
    args = ["--server", server.url, "--token", server.token, "--avatar", "demo", "--size",
            "32", "--quiet"]
    out = tmp_path / "talk"
    done = run_main(client_main, ["stream", *args, "--motion", "talk_calm", "--fps", "5",
                                  "--out", out], capsys)
    assert done.returncode == 0, done.stderr
    frames = sorted(out.glob("*.jpg"))
    assert len(frames) >= 10  # 4 s of talk_calm at 5 fps, every frame saved
    assert f"wrote {len(frames)} frames" in done.stdout
    bad = run_main(client_main, ["stream", *args, "--motion", "talk_clam", "--out",
                                 tmp_path / "bad"], capsys)
    assert bad.returncode == 1
    assert "'talk_clam'" in bad.stderr and "talk_calm" in bad.stderr and "smile" in bad.stderr
