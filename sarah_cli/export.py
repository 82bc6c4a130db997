"""sarah-export: motion out of the toolkit, as SMPL-X parameters (AMASS layout), BVH and glTF.

Sources: motion.npz files written by sarah-generate, or one person of a prepared sequence
(--shards with --sequence). Each source gives <out>/<name>.smplx.npz, <out>/<name>.bvh and
<out>/<name>.glb (or those --format names), and one line each with the joint residual between
the motion and the exported rigid body, and how far the body's head turns from the motion's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sarah_cli.arguments import HelpFormatter, non_negative_int, positive_int

EXIT_ERROR = 2
FORMATS = ("smplx", "bvh", "glb")


def _formats(text: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(n.strip().lower() for n in text.split(",") if n.strip()))
    unknown = [n for n in names if n not in FORMATS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"--format takes a comma list of {', '.join(FORMATS)}; "
                                         f"got {text!r}")
    return names


def build_parser() -> argparse.ArgumentParser:
    from sarah_data.export.bvh import UNITS
    from sarah_data.export.kinematics import POSE_SOURCES
    from sarah_data.export.smplx_params import UP_AXES

    parser = argparse.ArgumentParser(
        prog="sarah-export", formatter_class=HelpFormatter,
        description="Write motion as SMPL-X parameters in the AMASS layout (.smplx.npz: poses, "
                    "trans, betas, gender, mocap_frame_rate, root_orient, pose_body, pose_hand, "
                    "pose_jaw, pose_eye), as a BVH of the SMPL-X skeleton and as binary glTF "
                    "(.glb: the skeleton animated, with a stick figure skinned to it, for game "
                    "engines and the web). The exported body "
                    "keeps the person's bone lengths and follows the motion's joints (its global "
                    "rotations turned onto them, the limbs by two-bone IK), so it is always a "
                    "valid rigid body; each output line reports how far its joints are from the "
                    "motion's own.")
    parser.add_argument("motion", nargs="*", type=Path,
                        help="motion.npz files written by sarah-generate")
    parser.add_argument("--shards", type=Path, help="a prepared shards folder: export ground "
                        "truth of --sequence instead of motion files")
    parser.add_argument("--sequence", help="sequence name in --shards")
    parser.add_argument("--person", help="person of --sequence (default: its first person)")
    parser.add_argument("--start", type=non_negative_int, default=0,
                        help="first frame of --sequence to export")
    parser.add_argument("--frames", type=positive_int, default=None,
                        help="frames of --sequence to export (default: to its end)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--format", type=_formats, default=FORMATS,
                        help=f"comma list of {', '.join(FORMATS)}")
    parser.add_argument("--up", choices=UP_AXES, default="y",
                        help="up axis of the SMPL-X parameters: y is ours (floor y = 0); z rotates "
                             "(x, y, z) -> (x, -z, y) as AMASS files are stored")
    parser.add_argument("--bvh-units", choices=sorted(UNITS), default="m",
                        help="BVH length unit: m (Blender's default import scale) or cm (most "
                             "game-engine importers)")
    parser.add_argument("--pose-from", choices=POSE_SOURCES, default="joints",
                        help="joints: each rotation turned as little as it must for the body's "
                             "bones to point at the motion's joints, knees and elbows bent by "
                             "two-bone IK so that ankles and wrists land on the motion's, the "
                             "pelvis lowered where the body's legs are too short for them (the "
                             "decoding chain moves joints and leaves their rotations: posed by "
                             "those alone, generated feet that stand skate); rotations: the "
                             "motion's global rotations and pelvis as they are")
    parser.add_argument("--body-model", type=Path, default=None,
                        help="a SMPL-X .npz used only for motion without a body shape (raw-input "
                             "generations, schema-1 shards): its rest skeleton with zero betas")
    return parser


def _validate(args, parser) -> None:
    if bool(args.motion) == bool(args.shards):
        parser.error("give motion.npz files or --shards with --sequence (one of the two)")
    if args.shards is not None and not args.sequence:
        parser.error("--shards needs --sequence")
    if args.shards is None and (args.sequence or args.person):
        parser.error("--sequence and --person go with --shards")
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file, not a folder")
    if args.body_model is not None and not args.body_model.is_file():
        parser.error(f"--body-model {args.body_model}: no such file")


def export_one(motion, args, neutral) -> list[str]:
    """Build every requested output in memory first (so a failure writes nothing), then write
    each atomically; returns the lines to print."""
    from sarah_data.export import BodyShape, bvh, gltf, smplx_params

    if not motion.shape.known and neutral is not None:
        motion.shape = BodyShape(neutral.betas, neutral.rest_joints, neutral.gender,
                                 f"{neutral.source} ({motion.shape.source})")
    fit = motion.fit(args.pose_from)  # one body, written in every format
    built = []
    if "smplx" in args.format:
        built.append((args.out / f"{motion.name}.smplx.npz", "smplx",
                      smplx_params.smplx_parameters(motion, fit, args.up)))
    if "bvh" in args.format:
        built.append((args.out / f"{motion.name}.bvh", "bvh", bvh.bvh_text(motion, fit, args.bvh_units)))
    if "glb" in args.format:
        built.append((args.out / f"{motion.name}.glb", "glb",
                      gltf.glb_bytes(*gltf.gltf_document(motion, fit))))
    args.out.mkdir(parents=True, exist_ok=True)
    lines = []
    for path, kind, payload in built:
        if kind == "smplx":
            smplx_params.save_npz(path, payload)
            detail = f"SMPL-X, {args.up} up, betas from {motion.shape.source}"
        elif kind == "bvh":
            bvh.save_text(path, payload)
            detail = f"BVH, {args.bvh_units}, ZYX Euler"
        else:
            gltf.save_glb(path, payload)
            detail = "binary glTF 2.0, m, y up"
        lines.append(f"wrote {path} ({motion.frames} frames, {detail}, posed from its "
                     f"{args.pose_from}); {fit.summary()}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _validate(args, parser)

    from sarah_data.export import ExportError, motion_from_file, motion_from_shards

    neutral = None
    if args.body_model is not None:
        from sarah_data.export.motion import neutral_shape

        try:
            neutral = neutral_shape(args.body_model)
        except ExportError as error:
            print(f"sarah-export: error: --body-model {error}", file=sys.stderr)
            return EXIT_ERROR
    if args.shards is not None:
        loaders = [(args.shards, lambda: motion_from_shards(args.shards, args.sequence, args.person,
                                                            args.start, args.frames))]
    else:
        loaders = [(path, lambda path=path: motion_from_file(path)) for path in args.motion]
    failed = 0
    for source, load in loaders:
        try:
            for line in export_one(load(), args, neutral):
                print(line)
        except ExportError as error:
            failed += 1
            print(f"sarah-export: {error}", file=sys.stderr)
    if failed:
        print(f"sarah-export: {failed} of {len(loaders)} sources not exported", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
