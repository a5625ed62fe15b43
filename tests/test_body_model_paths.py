"""Where the body-model files are: one resolver, in a fixed order."""

import subprocess
import sys
from pathlib import Path

from avatar_core.body.model_paths import (
    BODY_MODELS_ENV,
    BodyModelFiles,
    resolve_body_models,
    synthetic_body_models,
)


def _cached_family(tmp_path, monkeypatch, synthetic_files):
    """The user cache (XDG) holding the synthetic family of seed 0, current generator."""
    cache = tmp_path / "xdg"
    (cache / "telesplat").mkdir(parents=True)
    (cache / "telesplat" / "synthetic-seed0").symlink_to(synthetic_files.root)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    return cache / "telesplat" / "synthetic-seed0"


def test_official_file_names():
    files = BodyModelFiles(Path("/models"))
    assert files.smplx_npz.name == "SMPLX_NEUTRAL.npz"
    assert files.flame_pkl.name == "FLAME_NEUTRAL.pkl"
    assert files.flame_static_embedding.name == "flame_static_embedding.pkl"
    assert files.flame_correspondence.name == "SMPL-X__FLAME_vertex_ids.npy"
    assert {files.mano_pkl(s).name for s in ("left", "right")} == {"MANO_LEFT.pkl",
                                                                   "MANO_RIGHT.pkl"}
    assert files.mano_correspondence.name == "MANO_SMPLX_vertex_ids.pkl"


def test_explicit_folder_then_environment_then_setting(tmp_path, monkeypatch):
    mine, env, setting = tmp_path / "mine", tmp_path / "env", tmp_path / "setting"
    monkeypatch.setenv(BODY_MODELS_ENV, str(env))
    assert resolve_body_models(mine, setting=setting).root == mine
    assert resolve_body_models(None, setting=setting).root == env
    monkeypatch.setenv(BODY_MODELS_ENV, "")  # empty means unset
    assert resolve_body_models(None, setting=setting).root == setting
    assert resolve_body_models("", setting=str(setting)).root == setting


def test_the_synthetic_family_is_the_last_resort(tmp_path, monkeypatch, synthetic_files):
    cached = _cached_family(tmp_path, monkeypatch, synthetic_files)
    monkeypatch.delenv(BODY_MODELS_ENV, raising=False)
    files = resolve_body_models()
    assert files.root == cached and files.smplx_npz.is_file()
    assert synthetic_body_models(seed=0).root == cached
    assert synthetic_body_models(synthetic_files.root).root == synthetic_files.root


def test_resolving_a_folder_does_not_load_the_studio(tmp_path):
    # The studio is imported only when the synthetic family is asked for.
    code = ("import sys\nfrom avatar_core.body.model_paths import resolve_body_models\n"
            "import avatar_core.studio_entry\n"  # the entry itself loads it lazily too
            f"resolve_body_models({str(tmp_path)!r})\n"
            "assert not any(m.startswith('avatar_core.synth') for m in sys.modules)\n"
            "assert 'avatar_core.demo' not in sys.modules\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=Path(__file__).resolve().parent.parent)
    assert run.returncode == 0, run.stderr
