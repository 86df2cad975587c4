"""Which DTU test views does a third training view help? Camera angles beside per-view scores of two runs.

  python -m frugalnerf_ns.tools.offline_tools eval <2-view run>/config.yml --per-view > two.log
  python -m frugalnerf_ns.tools.offline_tools eval <3-view run>/config.yml --per-view > three.log
  python scripts/diagnostics/dtu_view_gain.py two.log three.log [--data ../shared/data/dtu/scan65] [--views 22 25 28]

For every test view: the angle between its viewing direction and each training view's, the nearest training
view with and without the last of --views, and the masked PSNR of both runs. Prints the table and the mean PSNR
change over the views whose nearest training view the added one becomes, against the rest: if the added view
only helped the views it looks like, the rest stay where they were.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Dict, List

import torch

ROOT = Path(__file__).resolve().parents[2]


def read_views(log: Path) -> Dict[str, Dict[str, float]]:
    """view name -> scores, from the ``VIEW {json}`` lines of ``offline_tools eval --per-view``."""
    views = {}
    for line in log.read_text(errors="replace").splitlines():
        if line.startswith("VIEW "):
            view = json.loads(line[5:])
            views[view["view"]] = view
    if not views:
        raise SystemExit(f"dtu_view_gain: error: {log} has no VIEW lines (run offline_tools eval with --per-view)")
    return views


def angle_degrees(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.rad2deg(torch.arccos((a @ b / (a.norm() * b.norm())).clamp(-1, 1))))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("fewer", type=Path, help="per-view eval log of the run without the added view")
    parser.add_argument("more", type=Path, help="per-view eval log of the run with it")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "dtu" / "scan65")
    parser.add_argument("--views", type=int, nargs="+", default=[22, 25, 28], help="training views, the added one last")
    args = parser.parse_args(argv)
    fewer, more = read_views(args.fewer), read_views(args.more)

    from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig

    cameras = {}
    for split in ("train", "test"):
        outputs = DTUDataParserConfig(data=args.data, train_views=tuple(args.views)).setup().get_dataparser_outputs(split)
        # OpenGL convention: a camera looks along its -z axis.
        for c2w, name in zip(outputs.cameras.camera_to_worlds, outputs.image_filenames):
            cameras[(split, Path(name).stem)] = -c2w[:3, 2]
    train = [(name, d) for (split, name), d in cameras.items() if split == "train"]
    added = next(name for name, _ in train if int(name) == args.views[-1])
    rows: List[dict] = []
    for (split, name), direction in cameras.items():
        if split != "test" or name not in fewer or name not in more:
            continue
        angles = {t: angle_degrees(direction, d) for t, d in train}
        without = min((a, t) for t, a in angles.items() if t != added)
        with_added = min((a, t) for t, a in angles.items())
        rows.append({"view": name, "nearest_without": without, "nearest_with": with_added,
                     "psnr_fewer": fewer[name]["psnr"], "psnr_more": more[name]["psnr"]})
    print("| test view | nearest training view without / with the added one (deg) | PSNR fewer | PSNR more | change |")
    print("|---|---|---|---|---|")
    for r in rows:
        (a0, t0), (a1, t1) = r["nearest_without"], r["nearest_with"]
        print(f"| {r['view']} | {t0} {a0:.1f} / {t1} {a1:.1f} | {r['psnr_fewer']:.2f} | {r['psnr_more']:.2f} | "
              f"{r['psnr_more'] - r['psnr_fewer']:+.2f} |")
    helped = [r for r in rows if r["nearest_with"][1] == added]
    rest = [r for r in rows if r["nearest_with"][1] != added]
    for label, group in (("nearest to the added view", helped), ("the rest", rest), ("all", rows)):
        if group:
            change = statistics.fmean(r["psnr_more"] - r["psnr_fewer"] for r in group)
            print(f"{label}: {len(group)} views, mean PSNR {statistics.fmean(r['psnr_fewer'] for r in group):.2f} -> "
                  f"{statistics.fmean(r['psnr_more'] for r in group):.2f} ({change:+.2f} dB)")


if __name__ == "__main__":
    main()
