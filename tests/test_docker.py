"""The container files in docker/, checked without a registry or a Docker daemon: every
``Dockerfile*`` copies only what the repository has (and .dockerignore keeps), and its default
command is a ``telesplat serve`` invocation that the real CLI parser accepts, with a health
check on /v1/health and volumes for the data folder and the body models; every
``compose*.yml`` service that serves does the same, builds from a Dockerfile that exists and
mounts the body models read-only where TELESPLAT_BODY_MODELS points."""

from __future__ import annotations

import fnmatch
import json
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from avatar_core.body.model_paths import BODY_MODELS_ENV
from avatar_core.cli import build_parser
from server.config import load_settings

ROOT = Path(__file__).resolve().parent.parent
DOCKER = ROOT / "docker"
DOCKERFILES = sorted(DOCKER.glob("Dockerfile*"))
COMPOSE_FILES = sorted(DOCKER.glob("compose*.yml")) + sorted(DOCKER.glob("compose*.yaml"))
HEALTH = "/v1/health"
DATA_DIR_ENV = "TELESPLAT_DATA_DIR"


@dataclass
class Dockerfile:
    path: Path
    copies: list[tuple[list[str], bool]] = field(default_factory=list)  # (sources, from stage)
    cmd: list[str] | None = None  # the last stage's
    healthcheck: str = ""
    volumes: list[str] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)


def _instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    out, pending = [], ""
    for line in text.splitlines():  # bounded by the file
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):  # a comment inside a continued instruction
            continue
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        full = (pending + stripped).strip()
        pending = ""
        word, _, rest = full.partition(" ")
        out.append((word.upper(), rest.strip()))
    assert not pending, "an instruction ends in a line continuation"
    return out


def _exec_or_shell(args: str) -> list[str]:
    return json.loads(args) if args.startswith("[") else shlex.split(args)


def _env_pairs(args: str) -> dict[str, str]:
    parts = shlex.split(args)
    if len(parts) == 2 and "=" not in parts[0]:  # legacy `ENV KEY value`
        return {parts[0]: parts[1]}
    return dict(p.split("=", 1) for p in parts)


def parse_dockerfile(path: Path) -> Dockerfile:
    df = Dockerfile(path)
    for word, args in _instructions(path.read_text()):
        if word == "FROM":  # a new stage: what counts is the last one's
            df.cmd, df.healthcheck, df.volumes, df.env = None, "", [], {}
        elif word in ("COPY", "ADD"):
            parts = _exec_or_shell(args) if args.startswith("[") else shlex.split(args)
            flags = [p for p in parts if p.startswith("--")]
            files = [p for p in parts if not p.startswith("--")]
            df.copies.append((files[:-1], any(f.startswith("--from=") for f in flags)))
        elif word == "CMD":
            df.cmd = _exec_or_shell(args)
        elif word == "HEALTHCHECK":
            df.healthcheck = args
        elif word == "VOLUME":
            df.volumes += _exec_or_shell(args)
        elif word == "ENV":
            df.env.update(_env_pairs(args))
    return df


def _ignored(name: str) -> bool:
    patterns = [p.strip() for p in (ROOT / ".dockerignore").read_text().splitlines()
                if p.strip() and not p.startswith("#")] if (ROOT / ".dockerignore").is_file() \
        else []
    return any(fnmatch.fnmatch(name, p.removeprefix("**/")) for p in patterns
               if not p.startswith("!"))


def serve_args(argv: list[str]):
    """The parsed `telesplat serve` arguments; fails the test on anything else."""
    assert argv[:2] == ["telesplat", "serve"], f"not a `telesplat serve` command: {argv}"
    try:
        args = build_parser().parse_args(argv[1:])
    except SystemExit as exc:  # argparse has printed why
        pytest.fail(f"`{shlex.join(argv)}` does not parse ({exc.code})")
    assert args.group == "serve"
    return args


def _data_dir(args, env: dict[str, str]) -> str:
    value = args.data_dir or env.get(DATA_DIR_ENV)
    assert value, "the data folder must be given (--data-dir or TELESPLAT_DATA_DIR) so that a " \
                  "volume can hold it"
    return str(value)


def test_the_container_files_are_found():
    assert {p.name for p in DOCKERFILES} >= {"Dockerfile", "Dockerfile.cuda"}
    assert "compose.yml" in {p.name for p in COMPOSE_FILES}


def test_the_dockerfile_reader_reads_what_docker_reads(tmp_path):
    path = tmp_path / "Dockerfile"
    path.write_text('FROM a AS b\nCMD ["x"]\nFROM c\n# note\nCOPY --chown=1 x \\\n  y /z/\n'
                    'COPY --from=b /w /w\nENV A=1 \\\n    B="two words"\nVOLUME /v\n'
                    'CMD telesplat serve --port 1\n')
    df = parse_dockerfile(path)
    assert df.copies == [(["x", "y"], False), (["/w"], True)]
    assert df.env == {"A": "1", "B": "two words"} and df.volumes == ["/v"]
    assert df.cmd == ["telesplat", "serve", "--port", "1"]


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_every_copy_source_is_in_the_build_context(path):
    for sources, from_stage in parse_dockerfile(path).copies:
        if from_stage:
            continue
        for source in sources:
            matches = list(ROOT.glob(source))
            assert matches, f"{path.name}: COPY {source}: not in the repository"
            assert not _ignored(Path(source).parts[0]), \
                f"{path.name}: COPY {source}: excluded by .dockerignore"


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_the_default_command_serves_with_health_check_and_volumes(path):
    df = parse_dockerfile(path)
    assert df.cmd is not None, f"{path.name} has no CMD"
    args = serve_args(df.cmd)
    assert args.host == "0.0.0.0", "a container must listen on every interface"
    assert HEALTH in df.healthcheck and f":{args.port or 8000}/" in df.healthcheck
    assert _data_dir(args, df.env) in df.volumes
    assert df.env.get(BODY_MODELS_ENV) in df.volumes, \
        f"{BODY_MODELS_ENV} must point at a VOLUME (the body-model folder)"
    settings = load_settings(environ=df.env)  # the image's TELESPLAT_* settings are valid
    assert str(settings.body_models) == df.env[BODY_MODELS_ENV]
    if path.name == "Dockerfile.cuda":
        assert settings.backend == "gsplat"


def _compose(path: Path) -> dict:
    yaml = pytest.importorskip("yaml", reason="no YAML parser installed (PyYAML)")
    data = yaml.safe_load(path.read_text())
    assert isinstance(data, dict) and isinstance(data.get("services"), dict), path.name
    return data


def _volume(entry) -> tuple[str, bool]:
    """(target, read-only) of a short (`src:dst[:ro]`) or long volume entry."""
    if isinstance(entry, dict):
        return entry["target"], bool(entry.get("read_only"))
    parts = entry.split(":")
    return parts[1], len(parts) > 2 and "ro" in parts[2].split(",")


def _services(path: Path):
    """(name, service, its Dockerfile or None, the command it runs) of every service."""
    for name, service in _compose(path)["services"].items():
        build = service.get("build")
        dockerfile = None
        if build is not None:
            context = path.parent / (build if isinstance(build, str) else build["context"])
            name_in = "Dockerfile" if isinstance(build, str) else build.get("dockerfile",
                                                                            "Dockerfile")
            dockerfile = (context / name_in).resolve()
            assert dockerfile.is_file(), f"{path.name}: {name}: no {dockerfile}"
            assert context.resolve() == ROOT, f"{name}: the build context is the repository"
        command = service.get("command")
        if isinstance(command, str):
            command = shlex.split(command)
        if command is None and dockerfile is not None:
            command = parse_dockerfile(dockerfile).cmd
        yield name, service, dockerfile, command


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_services_that_serve_are_checked_and_healthy(path):
    serving = 0
    for name, service, dockerfile, command in _services(path):
        if not command or command[:2] != ["telesplat", "serve"]:
            continue  # e.g. a Ray worker of a cluster file: its Dockerfile is checked above
        serving += 1
        args = serve_args(command)
        env = dict(parse_dockerfile(dockerfile).env) if dockerfile else {}
        env.update(service.get("environment") or {})
        health = " ".join(service.get("healthcheck", {}).get("test", []))
        assert HEALTH in health, f"{path.name}: {name}: the health check must hit {HEALTH}"
        mounts = dict(_volume(v) for v in service.get("volumes", []))
        assert _data_dir(args, env) in mounts, f"{name}: no volume for the data folder"
        models = env.get(BODY_MODELS_ENV)
        assert models in mounts, f"{name}: {BODY_MODELS_ENV} must point at a mounted folder"
        assert mounts[models], f"{name}: the body models are mounted read-only"
    if path.name == "compose.yml":
        assert serving == 2  # the CPU and the GPU server


def test_the_gpu_service_reserves_a_gpu():
    services = _compose(DOCKER / "compose.yml")["services"]
    gpu = services["telesplat-gpu"]
    assert "gpu" in gpu.get("profiles", [])
    devices = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert any("gpu" in d.get("capabilities", []) for d in devices)
    assert gpu["build"]["dockerfile"] == "docker/Dockerfile.cuda"
    assert "profiles" not in services["telesplat"]  # `docker compose up` starts the CPU one
