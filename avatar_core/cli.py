"""The `telesplat` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

DEFAULT_CAPTURE_MOTIONS = "smile+grin+mouth_open,thumbs_up+peace+talk_calm,sad+angry+clapping"
BODY_MODELS_HELP = ("body-model folder, official file names (default: $TELESPLAT_BODY_MODELS, "
                    "else the synthetic family)")


def _add_body_models(parser: argparse.ArgumentParser) -> None:
    """``--body-models DIR``, resolved by avatar_core.body.model_paths. ``--models`` was its
    name on render and eval (the synthetic folder); kept hidden for the scripts that use it."""
    parser.add_argument("--body-models", type=Path, default=None, dest="body_models",
                        help=BODY_MODELS_HELP)
    parser.add_argument("--models", type=Path, dest="body_models",
                        help=argparse.SUPPRESS)


def _make_synthetic(args: argparse.Namespace) -> int:
    from .synth.model_writer import write_synthetic_models

    files = write_synthetic_models(args.out, seed=args.seed, resolution=args.resolution,
                                   num_identities=args.identities)
    print(f"wrote synthetic SMPL-X / FLAME / MANO files to {files.root}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from .synth.body_demo import render_demo

    with tqdm(total=args.frames, desc="rendering demo", unit="frame") as bar:
        out = render_demo(args.out, model_dir=args.models, frames=args.frames, size=args.size,
                          fps=args.fps, identity=args.identity,
                          progress=lambda i, n: bar.update(i - bar.n))
    print(f"wrote {out}")
    return 0


def _render(args: argparse.Namespace) -> int:
    from .pipeline import render_sequence
    from .render.types import RenderRequest

    request = RenderRequest(backend=args.backend, sh_degree=args.sh_degree, budget=args.budget,
                            background=tuple(args.background))
    with tqdm(total=args.frames, desc="rendering", unit="frame") as bar:
        def progress(i: int, n: int) -> None:
            bar.total = n
            bar.update(i - bar.n)

        out = render_sequence(args.avatar, args.motion, args.camera, args.out, size=args.size,
                              fps=args.fps, frames=args.frames, model_dir=args.body_models,
                              request=request, progress=progress)
    print(f"wrote {out}")
    return 0


def _capture(args: argparse.Namespace) -> int:
    from .synth.capture import CaptureSpec, capture, count_views, parse_sequences
    from .synth.trackers import parse_tracker_noise

    cross = args.cross_identity
    if cross is None:
        cross = 1 if args.identity == 0 else 0  # the other of the two stock identities
    cross = None if cross < 0 else cross
    spec = CaptureSpec(
        sequences=parse_sequences(args.motions), identity=args.identity,
        num_cameras=args.cameras, resolution=args.resolution, max_frames=args.max_frames,
        holdout_cameras=tuple(args.holdout_cameras.split(",")) if args.holdout_cameras else None,
        holdout_sequences=args.holdout_sequences, cross_identity=cross,
        supersample=args.supersample, workers=args.workers, seed=args.seed,
        trackers=args.trackers, tracker_noise=parse_tracker_noise(args.tracker_noise))
    with tqdm(total=count_views(spec), desc="capturing", unit="view") as bar:
        out = capture(args.out, spec, model_dir=args.models,
                      progress=lambda i, n: bar.update(i - bar.n))
    print(f"wrote dataset {out}")
    return 0


def _motion_strip(args: argparse.Namespace) -> int:
    from .dataset.preview import write_png
    from .motion.library import motion_names
    from .synth.preview import motion_strip

    names = args.motions.split(",") if args.motions else [
        *motion_names("expressions"), *motion_names("gestures")]
    with tqdm(total=len(names), desc="posing", unit="motion") as bar:
        img = motion_strip(names, identity=args.identity, camera=args.camera, size=args.size,
                           columns=args.columns, focus=args.focus, model_dir=args.models,
                           progress=lambda i, n: bar.update(i - bar.n))
    print(f"wrote {write_png(args.out, img)}")
    return 0


def _webcam_eval(args: argparse.Namespace) -> int:
    from .synth.tracking_eval.protocol_report import (
        protocol_markdown,
        run_protocol,
        write_protocol,
    )

    try:
        identities = [int(x) for x in args.identities.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"--identities takes integers, got {args.identities!r}") from None
    framings = [x.strip() for x in args.framings.split(",") if x.strip()]
    drives = [x.strip() for x in args.drives.split(",") if x.strip()]
    if args.max_frames is not None and args.max_frames < 2:
        raise SystemExit("--max-frames must be at least 2")
    if args.score_size < 16:
        raise SystemExit("--score-size must be at least 16")
    runs: list = []
    with tqdm(desc="webcam protocol", unit="frame") as bar:
        summary = run_protocol(identities, framings, args.fps, max_frames=args.max_frames,
                               score_size=(args.score_size, args.score_size * 3 // 4),
                               drives=drives, model_dir=args.models, runs_out=runs,
                               progress=lambda name, i, n: bar.update(1))
    js, md = write_protocol(summary, args.out)
    if args.keep_frames:
        import pickle

        with open(args.out / "runs.pkl", "wb") as f:  # our own output, read back by us
            pickle.dump(runs, f)
    print(protocol_markdown(summary))
    print(f"wrote {js}, {md}")
    return 0


def webcam_fit_config(args):
    """The FitConfig `eval --protocol webcam` fits with, or None for the live path's own: the
    live fit (arm cues included) with --embedding / --world-weight / --image-z-weight changed,
    or with --no-arm-cues the 2D fit the cues were measured against."""
    if not (args.embedding or args.world_weight or args.image_z_weight or args.no_arm_cues):
        return None
    import dataclasses

    from .track.fit.embedding import load_embedding
    from .track.fit.sequence import SequenceFitConfig, live_config

    base = SequenceFitConfig() if args.no_arm_cues else live_config()
    return dataclasses.replace(
        base.fit, embedding=load_embedding(args.embedding) if args.embedding else None,
        world_weight=args.world_weight, image_z_weight=args.image_z_weight)


def _eval(args: argparse.Namespace) -> int:
    from .metrics.evaluate import evaluate
    from .metrics.report import result_markdown

    if args.protocol == "webcam":
        from .metrics.webcam import evaluate_webcam, webcam_markdown

        fit_config = webcam_fit_config(args)
        with tqdm(desc="evaluating webcam", unit="frame") as bar:
            result = evaluate_webcam(
                args.avatar, args.dataset, max_frames=args.max_views,
                frame_stride=args.frame_stride, size=args.size, out_dir=args.out,
                model_dir=args.body_models, fit_config=fit_config,
                progress=lambda i, n: (setattr(bar, "total", n), bar.update(i - bar.n)))
        print(webcam_markdown(result).split("\n## ")[0].rstrip())
        return 0

    with tqdm(desc=f"evaluating {args.protocol}", unit="view") as bar:
        def progress(i: int, n: int) -> None:
            bar.total = n
            bar.update(i - bar.n)

        result = evaluate(args.avatar, args.dataset, args.protocol, fusion=not args.no_fusion,
                          max_views=args.max_views, frame_stride=args.frame_stride,
                          out_dir=args.out, size=args.size, model_dir=args.body_models,
                          progress=progress)
    print(result_markdown(result).split("\n## ")[0].rstrip())  # the headline table
    if args.out:
        print(f"wrote {args.out / 'metrics.json'}, {args.out / 'metrics.md'}")
    return 0


def _train(args: argparse.Namespace) -> int:
    import logging

    from .train.config import load_config
    from .train.trainer import Trainer

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.resume:
        trainer = Trainer.resume(args.out, args.dataset, body_model=args.body_models,
                                 iterations=args.iterations, device=args.device)
    else:
        from dataclasses import replace

        from .train.config import TrainConfig

        config = load_config(args.config) if args.config else TrainConfig()
        overrides = {"iterations": args.iterations, "device": args.device}
        config = replace(config, **{k: v for k, v in overrides.items() if v is not None})
        trainer = Trainer(args.dataset, config, args.out, body_model=args.body_models)
    from protocol.jobs import small_job_warning

    warning = small_job_warning(trainer.config.iterations)
    if warning:
        print(f"telesplat: {warning}", file=sys.stderr)
    with tqdm(total=trainer.config.iterations, initial=trainer.iteration, desc="training",
              unit="it") as bar:
        def progress(event: dict) -> None:
            bar.update(event["iteration"] - bar.n)
            if event["type"] == "progress" and event["loss"] is not None:
                bar.set_postfix(loss=f"{event['loss']:.4f}", psnr=event["psnr"] and
                                f"{event['psnr']:.2f}", gaussians=event["num_gaussians"])

        trainer.progress = progress
        out = trainer.train()
    print(f"wrote avatar {out}")
    return 0


def _film_enroll_video(args: argparse.Namespace) -> int:
    from ..synth.enroll_video import EnrollVideoSpec, film_enroll_video

    spec = EnrollVideoSpec(seconds=args.seconds, fps=args.fps, width=args.width,
                           height=args.height, yaw_deg=args.yaw)
    with tqdm(total=spec.num_frames, desc="filming", unit="frame") as bar:
        path = film_enroll_video(args.out, spec, params_out=args.true_params,
                                 progress=lambda i, n: bar.update(i - bar.n))
    print(f"wrote {path}")
    return 0


def _demo_avatar(args: argparse.Namespace) -> int:
    import logging

    from .demo import ensure_demo_avatar

    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    bars: dict[str, tqdm] = {}

    def progress(stage: str, done: int, total: int) -> None:
        bar = bars.get(stage)
        if bar is None:
            unit = "view" if stage == "capture" else "it"
            bar = bars[stage] = tqdm(total=total, desc=f"demo avatar: {stage}", unit=unit)
        bar.update(done - bar.n)

    try:
        path = ensure_demo_avatar(args.cache, progress)
    finally:
        for bar in bars.values():
            bar.close()
    print(f"demo avatar: {path}")
    return 0


def _track_fetch_models(args: argparse.Namespace) -> int:
    from .track.models import ModelFetchError, cache_dir, fetch_models

    try:
        paths = fetch_models(args.cache, prelu=args.prelu, force=args.force, progress=print)
    except ModelFetchError as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2
    print(f"{len(paths)} ONNX models in {cache_dir(args.cache) / 'onnx'}")
    return 0


def _track_landmarks(args: argparse.Namespace) -> int:
    import cv2

    from .track.draw import draw_result
    from .track.image import decode_image
    from .track.models import ModelFetchError
    from .track.tracker import Tracker
    from .track.types import TrackingInputError

    try:
        frame = decode_image(Path(args.image).read_bytes())
        tracker = Tracker(models=args.cache, mask=args.mask)
        for _ in range(args.frames):  # > 1: tracking mode, the ROI from the landmarks
            result = tracker.track(frame)
    except (OSError, TrackingInputError, ModelFetchError) as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2
    if not cv2.imwrite(str(args.out), draw_result(frame, result)):
        print(f"telesplat: error: could not write {args.out}", file=sys.stderr)
        return 2
    hands = ", ".join(h.handedness for h in result.hands) or "none"
    print(f"face: {'yes' if result.face else 'no'}; hands: {hands}; "
          f"body: {'yes' if result.pose else 'no'} -> {args.out}")
    return 0


def _track_fit(args: argparse.Namespace) -> int:
    from .track.fit.video import default_sequence_fit, frames_from, track_params, write_params
    from .track.models import ModelFetchError
    from .track.tracker import Tracker
    from .track.types import TrackingInputError

    source = args.webcam if args.webcam is not None else str(args.image or args.video)
    try:
        tracker = Tracker(models=args.cache, iris=True)
        sequence_fit = default_sequence_fit(args.fov, smoothing=not args.no_smoothing,
                                            body_models=args.body_models)
        with tqdm(total=args.frames, unit="frame", desc="tracking") as bar:
            params = track_params(frames_from(source, args.frames), sequence_fit, tracker,
                                  with_transl=args.with_transl, progress=lambda: bar.update())
        out = write_params(params, args.out)
    except (OSError, ValueError, TrackingInputError, ModelFetchError) as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2
    print(f"{len(params)} frames of SMPL-X parameters -> {out}")
    return 0


def _track_build_embedding(args: argparse.Namespace) -> int:
    from .synth.embedding_build import build_embedding
    from .synth.embedding_spec import BuildSpec

    try:
        spec = BuildSpec(train_identities=tuple(args.identities),
                         held_out_identities=tuple(args.held_out_identities),
                         train_clips=tuple(args.clips), held_out_clips=tuple(args.held_out_clips),
                         frames_per_view=args.frames_per_view, seed=args.seed)
        total = 0 if args.from_samples else spec.count()
        with tqdm(total=total, unit="frame", desc="studio frames") as bar:
            emb, report = build_embedding(spec, args.body_models, progress=lambda: bar.update(),
                                          samples_out=args.samples,
                                          samples_in=args.from_samples)
        npz, sidecar = emb.save(args.out)
    except (OSError, ValueError) as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2
    held = report.get("held_out", {})
    for name, row in held.items():
        print(f"{name:24s} {report['mode_per_row'].get(name, 'none'):8s} mean "
              f"{row['before_px']:6.2f} -> {row['after_px']:6.2f} px, median "
              f"{row['before_median_px']:6.2f} -> {row['after_median_px']:6.2f} px "
              f"({row['samples']} held-out samples)")
    print(f"embedding -> {npz} (+ {sidecar.name})")
    return 0


def _add_track(groups: argparse._SubParsersAction) -> None:
    track = groups.add_parser(
        "track", help="monocular tracking (MediaPipe models as ONNX); "
        "'telesplat track VIDEO|--webcam --out PARAMS' is short for 'telesplat track fit'")
    track_cmds = track.add_subparsers(dest="command", required=True)
    fetch = track_cmds.add_parser(
        "fetch-models", help="download the mediapipe wheel (pip download, never installed), "
        "extract its TFLite models and convert them to ONNX, cached")
    fetch.add_argument("--cache", type=Path, default=None,
                       help="cache folder (default: $TELESPLAT_MEDIAPIPE_CACHE or "
                            "~/.cache/telesplat/mediapipe)")
    fetch.add_argument("--prelu", choices=["rewrite", "op"], default="rewrite",
                       help="PReLU as Relu(x) + alpha*Min(x, 0) (faster) or the PRelu op")
    fetch.add_argument("--force", action="store_true", help="convert again even if cached")
    fetch.set_defaults(func=_track_fetch_models)
    draw = track_cmds.add_parser(
        "landmarks", help="track one image (JPEG/PNG) and draw the face, hand and body "
        "landmarks on it, for eyeballing")
    draw.add_argument("image", type=Path)
    draw.add_argument("--out", type=Path, required=True, help="output PNG")
    draw.add_argument("--mask", action="store_true", help="also tint the person mask")
    draw.add_argument("--frames", type=int, default=2,
                      help="track the image this many times (>= 2: ROIs from landmarks)")
    draw.add_argument("--cache", type=Path, default=None, help="model cache folder")
    draw.set_defaults(func=_track_landmarks)
    fit = track_cmds.add_parser(
        "fit", help="track a video, the webcam or an image and fit SMPL-X parameters per "
        "frame, written as a motion file (.json or .npz) for render/stream --motion")
    src = fit.add_mutually_exclusive_group(required=True)
    src.add_argument("video", nargs="?", type=Path, help="video file")
    src.add_argument("--webcam", type=int, nargs="?", const=0, metavar="INDEX",
                     help="track the webcam (camera INDEX, default 0)")
    src.add_argument("--image", type=Path, help="one JPEG/PNG image")
    fit.add_argument("--out", type=Path, required=True, help="PARAMS.npz or PARAMS.json")
    fit.add_argument("--frames", type=int, default=None, help="at most this many frames")
    fit.add_argument("--fov", type=float, default=60.0,
                     help="the camera's horizontal field of view, degrees")
    fit.add_argument("--no-smoothing", action="store_true", help="no One Euro smoothing")
    fit.add_argument("--with-transl", action="store_true",
                     help="keep transl (the subject's place in front of the camera)")
    fit.add_argument("--cache", type=Path, default=None, help="model cache folder")
    _add_body_models(fit)
    fit.set_defaults(func=_track_fit)
    _add_build_embedding(track_cmds)
    _add_build_world_correction(track_cmds)


def _track_build_world_correction(args: argparse.Namespace) -> int:
    from .synth.world_correction_build import (
        CorrectionSpec,
        build_world_correction,
        write_asset,
    )

    try:
        spec = CorrectionSpec(identities=tuple(args.identities), framings=tuple(args.framings),
                              take=tuple(args.take), fps=args.fps, max_frames=args.max_frames,
                              ridge=args.ridge)
        bars: dict[str, tqdm] = {}

        def progress(name: str, done: int, total: int) -> None:
            if name not in bars:  # one bar per condition filmed
                bars[name] = tqdm(total=total, unit="frame", desc=name)
            bars[name].update(done - bars[name].n)

        corr, report = build_world_correction(spec, args.work, args.body_models, progress)
        for bar in bars.values():
            bar.close()
        out = write_asset(corr, report, args.out)
    except (OSError, ValueError) as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2
    errors = report["train_bone_error_deg"]
    for part in ("upper", "fore"):
        before, after = (errors[k][f"{part}_median"] for k in ("blazepose", "corrected"))
        print(f"{part:5s} arm bones, median deg: BlazePose {before:.1f} -> corrected "
              f"{after:.1f} (training frames)")
    print(f"world correction -> {out} (+ {out.with_suffix('.json').name}), "
          f"{report['frames']} frames")
    return 0


def _add_build_world_correction(track_cmds: argparse._SubParsersAction) -> None:
    from .synth import world_correction_build as wcb

    build = track_cmds.add_parser(
        "build-world-correction", help="fit the correction of BlazePose's world arm bones on "
        "studio renders (identities and motions the webcam protocol does not score); writes "
        "OUT.npz + OUT.json")
    build.add_argument("--out", type=Path, required=True, help="OUT.npz (and OUT.json)")
    build.add_argument("--work", type=Path, required=True,
                       help="folder for the recordings (reused when present)")
    build.add_argument("--identities", type=int, nargs="+", default=list(wcb.TRAIN_IDENTITIES))
    build.add_argument("--framings", nargs="+", default=list(wcb.TRAIN_FRAMINGS))
    build.add_argument("--take", nargs="+", default=list(wcb.TRAIN_TAKE),
                       help="library motions played one after another")
    build.add_argument("--fps", type=float, default=10.0)
    build.add_argument("--max-frames", type=int, default=None, help="per condition")
    build.add_argument("--ridge", type=float, default=wcb.CorrectionSpec.ridge)
    build.add_argument("--body-models", type=Path, default=None,
                       help="the synthetic family's folder (default: a cache folder beside "
                            "the default models, written on first use)")
    build.set_defaults(func=_track_build_world_correction)


def _add_build_embedding(track_cmds: argparse._SubParsersAction) -> None:
    from .synth.embedding_spec import (
        HELD_OUT_CLIPS,
        HELD_OUT_IDENTITIES,
        TRAIN_CLIPS,
        TRAIN_IDENTITIES,
    )

    build = track_cmds.add_parser(
        "build-embedding", help="fit the learned landmark embedding (where each MediaPipe "
        "landmark lies on the body model) on studio renders, validated on held-out "
        "identities and clips; writes OUT.npz + OUT.json")
    build.add_argument("--out", type=Path, required=True, help="OUT.npz (and OUT.json)")
    build.add_argument("--identities", type=int, nargs="+", default=list(TRAIN_IDENTITIES),
                       help="synthetic identities to fit on")
    build.add_argument("--held-out-identities", type=int, nargs="*",
                       default=list(HELD_OUT_IDENTITIES), help="identities to validate on")
    build.add_argument("--clips", nargs="+", default=list(TRAIN_CLIPS),
                       help="library clips to fit on")
    build.add_argument("--held-out-clips", nargs="*", default=list(HELD_OUT_CLIPS),
                       help="library clips to validate on")
    build.add_argument("--frames-per-view", type=int, default=2,
                       help="frames per (identity, clip, yaw, framing)")
    build.add_argument("--seed", type=int, default=0)
    build.add_argument("--samples", type=Path, default=None,
                       help="also write the studio samples (npz) for bench/webcam_embedding.py")
    build.add_argument("--from-samples", type=Path, default=None,
                       help="fit on samples a previous --samples wrote instead of filming")
    build.add_argument("--body-models", type=Path, default=None,
                       help="the synthetic family's folder (default: a cache folder beside "
                            "the default models, written on first use)")
    build.set_defaults(func=_track_build_embedding)


COMMAND_PLUGINS = "telesplat.commands"


def _add_plugins(groups: argparse._SubParsersAction) -> None:
    """Subcommands that other packages register under the ``telesplat.commands`` entry-point
    group (``serve`` comes from the server this way): the engine never imports them by name."""
    from importlib.metadata import entry_points

    for ep in sorted(entry_points(group=COMMAND_PLUGINS), key=lambda e: e.name):
        ep.load()(groups)


def _budget(text: str) -> int | float:
    value = float(text)
    return value if "." in text else int(value)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="telesplat", description=__doc__)
    groups = parser.add_subparsers(dest="group", required=True)
    body = groups.add_parser("body", help="parametric body models")
    body_cmds = body.add_subparsers(dest="command", required=True)

    make = body_cmds.add_parser("make-synthetic", help="write synthetic SMPL-X/FLAME/MANO files")
    make.add_argument("--out", type=Path, required=True, help="output folder")
    make.add_argument("--seed", type=int, default=0)
    make.add_argument("--resolution", type=float, default=1.0,
                      help="mesh density; 1.0 gives the SMPL-X vertex count or more")
    make.add_argument("--identities", type=int, default=2)
    make.set_defaults(func=_make_synthetic)

    demo = body_cmds.add_parser("demo", help="render the posed synthetic upper body")
    demo.add_argument("--out", type=Path, required=True, help=".mp4 video or .png strip")
    demo.add_argument("--models", type=Path, default=None,
                      help="synthetic model folder (generated there if missing; default: cache)")
    demo.add_argument("--frames", type=int, default=96)
    demo.add_argument("--size", type=int, default=384)
    demo.add_argument("--fps", type=int, default=24)
    demo.add_argument("--identity", type=int, default=0)
    demo.set_defaults(func=_demo)

    synth = groups.add_parser("synth", help="the software capture studio")
    synth_cmds = synth.add_subparsers(dest="command", required=True)
    cap = synth_cmds.add_parser("capture", help="film the synthetic actor into a dataset")
    cap.add_argument("--out", type=Path, required=True, help="dataset folder to create")
    cap.add_argument("--identity", type=int, default=0)
    cap.add_argument("--motions", default=DEFAULT_CAPTURE_MOTIONS,
                     help="sequences separated by ',', motions within one joined by '+'")
    cap.add_argument("--cameras", type=int, default=17)
    cap.add_argument("--resolution", type=int, default=512)
    cap.add_argument("--max-frames", type=int, default=None, help="per sequence")
    cap.add_argument("--holdout-cameras", default=None,
                     help="comma-separated camera names (default: a front-arc camera next to "
                          "azimuth 0, never the front camera itself)")
    cap.add_argument("--holdout-sequences", type=int, default=1,
                     help="the last N sequences are held out for self-reenactment")
    cap.add_argument("--cross-identity", type=int, default=None,
                     help="identity that performs the held-out motions (default: another "
                          "one; -1: none)")
    cap.add_argument("--trackers", choices=["simulated", "exact"], default="simulated",
                     help="simulated: body-tracker SMPL-X + exact FLAME/MANO (as a real "
                          "studio); exact: the true SMPL-X only")
    cap.add_argument("--tracker-noise", default="",
                     help="tracker errors that survive fusion: 'studio' (the noisy-tracker "
                          "benchmark's), NAME=VALUE,... (TrackerNoise fields) or both: "
                          "'studio,hand_swap_frames=0'; default none")
    cap.add_argument("--supersample", type=int, default=2)
    cap.add_argument("--workers", type=int, default=2)
    cap.add_argument("--seed", type=int, default=0)
    cap.add_argument("--models", type=Path, default=None, help="synthetic model folder")
    cap.set_defaults(func=_capture)

    strip = synth_cmds.add_parser("preview", help="library motions at their peak, one camera")
    strip.add_argument("--out", type=Path, required=True, help="PNG to write")
    strip.add_argument("--motions", default=None,
                       help="comma-separated (default: every expression and gesture)")
    strip.add_argument("--identity", type=int, default=0)
    strip.add_argument("--camera", default=None, help="default: the centre front camera")
    strip.add_argument("--size", type=int, default=256)
    strip.add_argument("--columns", type=int, default=8)
    strip.add_argument("--focus", choices=["body", "face"], default="body")
    strip.add_argument("--models", type=Path, default=None, help="synthetic model folder")
    strip.set_defaults(func=_motion_strip)

    web = synth_cmds.add_parser(
        "webcam-eval", help="the webcam protocol on the studio: track + fit + score a take "
        "with the arms moving, per identity and framing, with the part attribution")
    web.add_argument("--out", type=Path, required=True,
                     help="folder for webcam_protocol.json and webcam_protocol.md")
    web.add_argument("--identities", default="0,1", help="comma-separated identities")
    web.add_argument("--framings", default="head_shoulders,waist_up",
                     help="comma-separated: head_shoulders, waist_up")
    web.add_argument("--fps", type=float, default=15.0, help="webcam frame rate")
    web.add_argument("--max-frames", type=int, default=None,
                     help="the first N frames of the take (a smoke run; the protocol is "
                          "the whole take, >= 10 s)")
    web.add_argument("--score-size", type=int, default=320, help="score camera width (4:3)")
    web.add_argument("--drives", default="live,embedding,true_body,true_body_face,true_all",
                     help="comma-separated: live (the tracked landmarks, today's fit), "
                          "embedding (+ the learned landmark embedding and image z), "
                          "true_body, true_body_face, true_all (those parts' 2D landmarks "
                          "from the truth), live_pose_hands (+ BlazePose's hand points for "
                          "declined hands), live_true_depth, true_all_arm_depth, "
                          "true_all_torso_depth, true_all_depth (+ the true depth of the "
                          "arms' / torso's body landmarks)")
    web.add_argument("--models", type=Path, default=None, help="synthetic model folder")
    web.add_argument("--keep-frames", action="store_true",
                     help="also write runs.pkl: every frame's true, fitted and smoothed "
                          "parameters (to recompute metrics or smoothing curves)")
    web.set_defaults(func=_webcam_eval)

    from .dataset.cli import register as register_dataset

    register_dataset(groups)

    from .enroll.cli import register as register_enroll

    register_enroll(groups, _add_body_models)
    film = synth_cmds.add_parser(
        "enroll-video", help="film the synthetic actor turning and gesturing (one camera, mp4)")
    film.add_argument("--out", type=Path, required=True, help="the .mp4 to write")
    film.add_argument("--seconds", type=float, default=4.0)
    film.add_argument("--fps", type=float, default=10.0)
    film.add_argument("--width", type=int, default=320)
    film.add_argument("--height", type=int, default=240)
    film.add_argument("--yaw", type=float, default=90.0, help="the turn either way, deg")
    film.add_argument("--true-params", type=Path, default=None,
                      help="also write the true per-frame parameters (.npz)")
    film.set_defaults(func=_film_enroll_video)

    render = groups.add_parser("render", help="render an avatar under a motion")
    render.add_argument("avatar", help="avatar package (folder or .zip) or synthetic[:IDENTITY]")
    render.add_argument("--motion", default="demo",
                        help="a built-in clip by name (demo, rest, or a library clip: smile, "
                             "talk_calm, ...: every name in 'telesplat-client motions list'), "
                             "or a .json / .npz parameter file")
    render.add_argument("--camera", default="orbit",
                        help="a camera preset: front, left, right, or orbit (a sweep from "
                             "left to right; one frame: the front), or a JSON camera file")
    render.add_argument("--out", type=Path, required=True, help="folder of PNGs or FILE.mp4")
    _add_body_models(render)
    render.add_argument("--size", type=int, default=512)
    render.add_argument("--fps", type=float, default=25.0)
    render.add_argument("--frames", type=int, default=None, help="at most this many frames")
    render.add_argument("--backend", default="auto", choices=["auto", "torch", "cpu", "gsplat"])
    render.add_argument("--sh-degree", type=int, default=None)
    render.add_argument("--budget", type=_budget, default=None,
                        help="render only the K (int) or fraction (float) most important splats")
    render.add_argument("--background", type=float, nargs=3, default=(1.0, 1.0, 1.0))
    render.set_defaults(func=_render)

    train = groups.add_parser("train", help="train an avatar on a dataset")
    train.add_argument("dataset", type=Path, help="dataset folder (Format v1)")
    train.add_argument("--out", type=Path, required=True,
                       help="output folder: checkpoints/, avatar/ (the package)")
    train.add_argument("--config", type=Path, default=None,
                       help=".json or .toml config; its optional 'preset' key picks the base: "
                            "default, quick, demo (the least that gives a usable avatar) or "
                            "test (smoke runs only)")
    train.add_argument("--resume", action="store_true", help="continue from OUT's checkpoint")
    train.add_argument("--iterations", type=int, default=None, help="total iterations")
    train.add_argument("--device", default=None, help="auto, cpu, cuda[:N]")
    _add_body_models(train)
    train.set_defaults(func=_train)

    ev = groups.add_parser("eval", help="evaluate an avatar on a dataset split")
    ev.add_argument("avatar", help="avatar package (folder or .zip) or synthetic[:IDENTITY]")
    ev.add_argument("dataset", type=Path, help="dataset folder")
    ev.add_argument("--protocol", required=True,
                    choices=["self-reenactment", "novel-view", "cross-identity", "webcam"])
    ev.add_argument("--out", type=Path, default=None,
                    help="folder for metrics.json, metrics.md and images/")
    ev.add_argument("--no-fusion", action="store_true",
                    help="drive with the body tracker's SMPL-X alone (the ablation)")
    ev.add_argument("--max-views", type=int, default=None, help="the first N views")
    ev.add_argument("--frame-stride", type=int, default=1, help="every K-th frame")
    ev.add_argument("--size", type=int, default=None, help="render width (default: dataset's)")
    ev.add_argument("--embedding", type=Path, default=None,
                    help="webcam protocol: the live fit with this learned landmark embedding "
                         "(.npz)")
    ev.add_argument("--world-weight", type=float, default=0.0,
                    help="webcam protocol: weight of BlazePose's world-z term in the fit")
    ev.add_argument("--image-z-weight", type=float, default=0.0,
                    help="webcam protocol: weight of BlazePose's image-z term in the fit")
    ev.add_argument("--no-arm-cues", action="store_true",
                    help="webcam protocol: fit without BlazePose's world bone directions and "
                         "the elbow hinge (the 2D fit; the live path has them)")
    _add_body_models(ev)
    ev.set_defaults(func=_eval)

    demo = groups.add_parser("demo-avatar", help="build (first run) or find the trained demo "
                             "avatar: synthetic capture + training, cached")
    demo.add_argument("--cache", type=Path, default=None,
                      help="cache folder (default: ~/.cache/telesplat/demo-avatar-vN)")
    demo.set_defaults(func=_demo_avatar)

    _add_track(groups)
    _add_plugins(groups)
    return parser


TRACK_COMMANDS = ("fetch-models", "landmarks", "fit", "-h", "--help", "build-embedding",
                  "build-world-correction")


def _expand_shorthands(argv: list[str]) -> list[str]:
    """`telesplat track VIDEO|--webcam ...` -> `telesplat track fit ...`."""
    if len(argv) > 1 and argv[0] == "track" and argv[1] not in TRACK_COMMANDS:
        return [argv[0], "fit", *argv[1:]]
    return argv


def main(argv: list[str] | None = None) -> int:
    argv = _expand_shorthands(list(sys.argv[1:] if argv is None else argv))
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
