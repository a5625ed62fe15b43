"""One body-model setting end to end, without licensed files: the synthetic family copied under
the official file names into a folder labelled non-synthetic (as a user's download), then
through the setting alone (TELESPLAT_BODY_MODELS, --body-models, the server's body_models) a
tiny avatar is trained, served, streamed and driven by a tracked image. Plus the resolver's
order, and the errors: a dataset needing real models, a missing file, a package loaded
against other model files."""

from __future__ import annotations

import asyncio
import json
import shutil

import cv2
import numpy as np
import pytest

from avatar_core.body.model_paths import (
    BODY_MODELS_ENV,
    OFFICIAL_FILES,
    BodyModelFiles,
    BodyModelsMissing,
    models_for_reference,
    models_for_source,
)
from avatar_core.cli import main as telesplat
from avatar_core.gaussians.loading import BodyModelMismatch, load_avatar
from avatar_core.gaussians.package import PackageError, faces_fingerprint, load_package
from client.cli import main as client_main
from protocol import Drive, Image, encode
from server.config import load_settings
from server.jobs.service import JobService, SubmitError
from server.jobs.store import NewJob, SQLiteJobStore
from server.jobs.worker import Worker, WorkerConfig
from server.registry import AvatarRegistry
from tests.dataset_fixtures import write_tiny_dataset
from tests.server_fixtures import is_type, recv_until, run_server, stream
from tests.test_track_drive import _astronaut_video, astronaut_jpeg
from tests.track_models import models_available, needs_models

STUDIO_ONLY = ("manifest.json", "gestures.npz", "identities")  # not in an official download
TINY_CONFIG = ('preset = "test"\ncheckpoint_interval = 1000\n[finetune]\nenabled = false\n'
               '[densify]\nenabled = false\n')


@pytest.fixture(autouse=True)
def _no_setting_from_outside(monkeypatch):
    monkeypatch.delenv(BODY_MODELS_ENV, raising=False)


def _official_copy(synthetic_files, folder, *, label: str = "licensed stand-in (test)"):
    """The synthetic family's files under the official names, with a non-synthetic label."""
    folder.mkdir(parents=True)
    for path in synthetic_files.root.iterdir():
        if path.name not in STUDIO_ONLY and path.is_file():
            shutil.copyfile(path, folder / path.name)
    (folder / "manifest.json").write_text(json.dumps({"synthetic": False, "source": label}))
    return BodyModelFiles(folder)


@pytest.fixture(scope="module")
def official(synthetic_files, tmp_path_factory):
    return _official_copy(synthetic_files, tmp_path_factory.mktemp("models") / "smplx")


# -- the resolver and its errors ------------------------------------------------------------


def test_the_copy_reads_as_real_models(official, synthetic_files):
    assert official.synthetic_seed() is None and official.identities() == []
    assert synthetic_files.synthetic_seed() == 0
    assert str(official.root) == official.describe()
    assert "synthetic family, seed 0" in synthetic_files.describe()


def test_real_sources_take_the_folder_in_the_resolver_order(official, tmp_path, monkeypatch):
    other = _official_copy(BodyModelFiles(official.root), tmp_path / "other")
    monkeypatch.setenv(BODY_MODELS_ENV, str(other.root))
    files, reference = models_for_source("vhap", official.root, setting=tmp_path / "none")
    assert files.root == official.root and reference == "SMPLX_NEUTRAL.npz"
    assert models_for_source("vhap", setting=official.root)[0].root == other.root  # env first
    monkeypatch.delenv(BODY_MODELS_ENV)
    assert models_for_reference("SMPLX_NEUTRAL.npz", setting=official.root).root == official.root


def test_synthetic_sources_keep_their_family(official, synthetic_files):
    # A folder of other models does not take over what the synthetic family made...
    files, reference = models_for_source("synthetic-seed0", official.root)
    assert files.root != official.root and files.synthetic_seed() == 0
    assert reference == "synthetic:seed0"
    # ...and a folder holding that very family is used as it is.
    assert models_for_reference("synthetic:seed0", synthetic_files.root).root \
        == synthetic_files.root


def test_a_dataset_needing_real_models_says_which_files_go_where():
    with pytest.raises(BodyModelsMissing) as err:
        models_for_source("EasyMocap SMPL-X fit")
    message = str(err.value)
    for name, _, _ in OFFICIAL_FILES:
        assert name in message
    assert "'EasyMocap SMPL-X fit'" in message
    assert "--body-models DIR" in message and BODY_MODELS_ENV in message
    assert "body_models" in message


def test_a_missing_file_is_named(official, tmp_path):
    folder = tmp_path / "half"
    folder.mkdir()
    shutil.copyfile(official.smplx_npz, folder / "SMPLX_NEUTRAL.npz")
    with pytest.raises(BodyModelsMissing, match=r"lacks smplx_vert_segmentation\.json;"):
        models_for_source("user", folder)
    with pytest.raises(BodyModelsMissing, match=r"lacks SMPLX_NEUTRAL\.npz, smplx_vert"):
        models_for_reference("SMPLX_NEUTRAL.npz", tmp_path / "empty")


def test_train_without_models_fails_before_any_work(official, tmp_path, capsys):
    data = write_tiny_dataset(tmp_path / "data", num_cameras=2, frames=2).root
    assert telesplat(["train", str(data), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "the dataset's parameters come from body model 'test'" in err
    assert "SMPLX_NEUTRAL.npz" in err and not (tmp_path / "run" / "avatar").exists()


def test_settings_read_the_body_models_folder(tmp_path):
    env = {"TELESPLAT_BODY_MODELS": str(tmp_path)}
    assert load_settings(environ=env).body_models == tmp_path
    assert load_settings(environ={"TELESPLAT_BODY_MODELS": ""}).body_models is None
    assert load_settings(environ=env, body_models=tmp_path / "x").body_models == tmp_path / "x"


def test_the_jobs_worker_passes_the_setting_to_the_training_process(tmp_path):
    store = SQLiteJobStore(tmp_path / "jobs.db")
    worker = Worker(store, tmp_path, lambda job, package: "unused",
                    WorkerConfig(body_models=str(tmp_path / "models")))  # not started
    job = store.create(NewJob(owner="alice", dataset="upload", dataset_path=str(tmp_path),
                              config={}, total=1))
    cmd = worker._command(job)
    assert cmd[cmd.index("--body-models") + 1] == str(tmp_path / "models")
    assert "--body-models" not in Worker(store, tmp_path, lambda j, p: "")._command(job)


def test_a_job_server_without_the_files_refuses_the_dataset_at_submission(official, tmp_path):
    half = tmp_path / "models"
    half.mkdir()
    shutil.copyfile(official.smplx_npz, half / "SMPLX_NEUTRAL.npz")
    service = JobService(tmp_path / "data", lambda job, package: "unused",
                         worker=WorkerConfig(body_models=str(half)))  # not started
    write_tiny_dataset(service.datasets_dir / "mine", num_cameras=2, frames=2)
    with pytest.raises(SubmitError) as err:
        service.submit_named("alice", "mine")
    assert err.value.status == 400 and "lacks smplx_vert_segmentation.json" in str(err.value)
    assert str(half) not in str(err.value)  # the client is not told the server's folders
    assert service.store.list() == []


# -- one avatar, trained on the folder and checked against another -------------------------


@pytest.fixture(scope="module")
def trained(official, tmp_path_factory):
    """`telesplat train` on a tiny non-synthetic dataset, the models from the environment."""
    root = tmp_path_factory.mktemp("e2e")
    data = write_tiny_dataset(root / "data", num_cameras=3, frames=2, width=32, height=24).root
    config = root / "tiny.toml"
    config.write_text(TINY_CONFIG)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(BODY_MODELS_ENV, str(official.root))
        assert telesplat(["train", str(data), "--out", str(root / "run"), "--config",
                          str(config), "--iterations", "4", "--device", "cpu"]) == 0
    return root / "run" / "avatar"


def test_the_package_records_the_model_it_was_bound_to(trained, official):
    package = load_package(trained)
    assert package.body.model == "SMPLX_NEUTRAL.npz"
    loaded = load_avatar(str(trained), official.root)
    assert loaded.files.root == official.root
    faces = loaded.animator.body_model.faces.cpu().numpy()
    assert package.body.faces_sha256 == faces_fingerprint(faces)


def test_other_model_files_are_refused_naming_both(trained, official, tmp_path):
    other = _official_copy(BodyModelFiles(official.root), tmp_path / "other-smplx")
    parts = json.loads(other.segmentation.read_text())
    del parts["leftHand"]  # another cut of the body: other triangles
    other.segmentation.write_text(json.dumps(parts))
    bound = load_package(trained).body
    with pytest.raises(BodyModelMismatch) as err:
        load_avatar(str(trained), other.root)
    message = str(err.value)
    assert "'SMPLX_NEUTRAL.npz'" in message and bound.faces_sha256[:16] in message
    assert str(other.root) in message and "fingerprint" in message.split("give")[1]
    assert str(trained) in message
    assert str(other.root) not in err.value.public  # what a server's client is told
    with pytest.raises(BodyModelMismatch) as err:  # an upload to a server with those files
        AvatarRegistry(tmp_path / "avatars", body_models=other.root).add_package(trained, "bob")
    assert bound.faces_sha256[:16] in str(err.value) and str(tmp_path) not in str(err.value)


def test_the_registry_takes_it_only_with_the_setting(trained, official, tmp_path, monkeypatch):
    with pytest.raises(PackageError, match="bound to body model 'SMPLX_NEUTRAL.npz', which "
                                           "this server does not have") as err:
        AvatarRegistry(tmp_path / "bare").add_package(trained, "alice")  # an upload: 422
    assert str(tmp_path) not in str(err.value)  # no server folder reaches a client
    served = AvatarRegistry(tmp_path / "served", body_models=official.root)
    rec = served.add_package(trained, "alice")
    assert served.open(rec.id).files.root == official.root
    monkeypatch.setenv(BODY_MODELS_ENV, str(tmp_path / "elsewhere"))
    flag = AvatarRegistry(tmp_path / "flag", body_models=official.root)  # `serve --body-models`
    assert flag.open(flag.add_package(trained, "alice").id).files.root == official.root
    monkeypatch.delenv(BODY_MODELS_ENV)
    restarted = AvatarRegistry(tmp_path / "served")  # the setting gone after a restart
    with pytest.raises(BodyModelsMissing) as err:
        restarted.open(rec.id)
    assert rec.id in str(err.value) and str(tmp_path) not in str(err.value)


def test_render_and_eval_take_the_folder(trained, official, tmp_path, capsys):
    out = tmp_path / "frames"
    base = ["render", str(trained), "--frames", "1", "--size", "32", "--out", str(out)]
    assert telesplat([*base, "--motion", "rest"]) == 2  # no setting: the files it needs
    assert "bound to body model 'SMPLX_NEUTRAL.npz'" in capsys.readouterr().err
    assert telesplat([*base, "--motion", "rest", "--body-models", str(official.root)]) == 0
    assert len(list(out.glob("frame_*.png"))) == 1
    # the demo clip poses named expressions, which official files do not name
    assert telesplat([*base, "--body-models", str(official.root)]) == 2
    assert "use --motion rest or a parameter file" in capsys.readouterr().err
    data = trained.parent.parent / "data"
    assert telesplat(["eval", str(trained), str(data), "--protocol", "novel-view",
                      "--max-views", "1", "--out", str(tmp_path / "eval"),
                      "--body-models", str(official.root)]) == 0
    assert (tmp_path / "eval" / "metrics.json").is_file()


@needs_models
def test_track_cli_fits_with_the_folder_from_the_environment(official, tmp_path,
                                                             monkeypatch, capsys):
    image = tmp_path / "face.jpg"
    image.write_bytes(astronaut_jpeg(0.5))
    out = tmp_path / "params.json"
    monkeypatch.setenv(BODY_MODELS_ENV, str(tmp_path / "nowhere"))
    assert telesplat(["track", "--image", str(image), "--out", str(out)]) == 2
    assert "lacks SMPLX_NEUTRAL.npz" in capsys.readouterr().err
    monkeypatch.setenv(BODY_MODELS_ENV, str(official.root))
    assert telesplat(["track", "--image", str(image), "--out", str(out)]) == 0
    frames = json.loads(out.read_text())
    assert len(frames) == 1 and np.isfinite(np.asarray(frames[0]["body_pose"])).all()


@pytest.mark.slow  # ~20 s alone plus the shared training; still part of `make test`
def test_served_with_the_setting_streams_and_tracks(trained, official, tmp_path):
    """The trained package as the server's demo avatar, its models from the setting alone."""
    with run_server(tmp_path / "server", demo_avatar=str(trained),
                    body_models=official.root) as srv:
        async def run():
            async with stream(srv) as ws:
                assert ws.welcome.avatar.num_gaussians == load_package(trained).avatar.num
                await ws.send(encode(Drive(seq=1, smplx={"jaw_pose": [0.2, 0.0, 0.0]})))
                frame = await recv_until(ws, is_type("frame", seq=1), timeout=60)
                picture = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
                assert picture is not None and picture.std() > 0
                if not models_available():  # the image step needs the landmark models
                    return
                await ws.send(encode(Image(seq=2, data=astronaut_jpeg())))
                frame = await recv_until(ws, is_type("frame", seq=2), timeout=120)
                assert frame.timings.track > 0
        asyncio.run(run())
        loaded = srv.ctx.registry.open("demo")
        assert loaded.files.root == official.root
        if models_available():  # the remote tracker fits here, on the same files
            video = tmp_path / "clip.avi"
            _astronaut_video(video, frames=1)
            assert client_main(["drive", "--server", srv.url, "--token", srv.token,
                                "--avatar", "demo", "--video", str(video), "--quiet",
                                "--out", str(tmp_path / "driven"),
                                "--body-models", str(official.root)]) == 0
            assert len(list((tmp_path / "driven").iterdir())) == 1
