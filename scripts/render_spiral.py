"""Render a spiral video of a trained FrugalNeRF run in one line and print where it is.

  python scripts/render_spiral.py outputs/<scene>/frugalnerf/<timestamp>/config.yml [--seconds 4] [--depth]

Runs nerfstudio's own ``ns-render spiral`` (so the result is what ns-render gives: for a FrugalNeRF run the
scene's spiral or orbit around the training cameras, full scale only, with progress lines; see
``frugalnerf_ns/tools/video.py``) and writes ``<run>/renders/spiral.mp4`` (``spiral-depth.mp4`` with --depth) unless
--output says otherwise.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="config.yml of a trained run")
    parser.add_argument("--output", type=Path, default=None, help="video file (default: <run>/renders/spiral.mp4)")
    parser.add_argument("--seconds", type=float, default=4.0, help="video length")
    parser.add_argument("--frame-rate", type=int, default=24)
    parser.add_argument("--downscale-factor", type=float, default=1.0, help="render at 1/N of the camera size")
    parser.add_argument("--depth", action="store_true", help="render the depth map instead of rgb")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        sys.exit(f"render_spiral: error: {args.config} is not a file (pass <run>/config.yml)")

    from frugalnerf_ns.ffmpeg_path import provide_ffmpeg
    from nerfstudio.scripts.render import SpiralRender

    provide_ffmpeg()  # this script writes a video like ns-render: the bundled ffmpeg when PATH has none

    output = args.output or args.config.parent / "renders" / ("spiral-depth.mp4" if args.depth else "spiral.mp4")
    output.parent.mkdir(parents=True, exist_ok=True)
    SpiralRender(
        load_config=args.config, output_path=output, seconds=args.seconds, frame_rate=args.frame_rate,
        downscale_factor=args.downscale_factor,
        rendered_output_names=["depth" if args.depth else "rgb"],
    ).main()
    print(f"render_spiral: wrote {output.resolve()}")
    return output


if __name__ == "__main__":
    main()
