"""The ``muscle-mss`` command: validate scenes, write the demo scene, run the demo and motions.

``muscle-mss validate SCENE`` checks every rule of DESIGN §4; ``muscle-mss demo-scene OUT``
writes the deterministic demo thigh scene and its ``preview.png``.
"""
from __future__ import annotations

import argparse
import os
import sys

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.scene import Scene


def scene_counts(scene: Scene) -> str:
    """One line with the numbers of muscles, bones, fibres and time points."""
    fibres = sum(fs.count for fs in scene.fibres.values())
    return (f"{len(scene.muscles)} muscles, {len(scene.bones)} bones, {fibres} fibres, "
            f"{len(scene.motion.times)} time points")


def cmd_validate(args) -> int:
    from .scene_io import check_scene
    scene, problems = check_scene(args.scene)
    if problems:
        for p in problems:
            print(f"error: {p}")
        print(f"{args.scene}: {len(problems)} problem{'s' if len(problems) > 1 else ''}")
        return 1
    print(f"ok: {scene_counts(scene)}")
    return 0


def write_demo_scene(out: str, size: str) -> Scene:
    """Write the demo scene folder ``out`` and its ``preview.png``; return the scene as read
    back and checked from the files."""
    from muscle_mss.core.demo_scene import demo_scene
    from .pictures import scene_preview
    from .scene_io import load_scene, write_scene
    write_scene(demo_scene(size), out)
    scene = load_scene(out)
    scene_preview(scene, os.path.join(out, "preview.png"))
    return scene


def cmd_demo_scene(args) -> int:
    scene = write_demo_scene(args.out, args.size)
    print(f"wrote {args.out} ({args.size}): {scene_counts(scene)}; "
          f"picture {os.path.join(args.out, 'preview.png')}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="muscle-mss",
        description="Muscle deformation during motion: mass-spring fibres, sphere collisions "
                    "and mean value coordinates (Janák & Kohout 2014).")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("validate", help="check a scene folder against every rule of the format")
    p.add_argument("scene", help="scene folder (muscles.vtm, fibres.vtm, bones.vtm, motion.csv)")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("demo-scene", help="write the demo thigh scene and preview.png")
    p.add_argument("out", help="folder to write")
    p.add_argument("--size", choices=("full", "small"), default="full",
                   help="full: 13 muscles x 64 fibres; small: a quick variant for tests")
    p.set_defaults(func=cmd_demo_scene)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except MuscleMSSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
