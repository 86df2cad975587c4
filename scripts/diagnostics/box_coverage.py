"""Which pixels of a DTU view can the field draw at all? The rays that miss the scene box, per view.

  python scripts/diagnostics/box_coverage.py [--data ../shared/data/dtu/scan65] [--views 22 25 28]

A ray that misses the box gets no samples: the render is the background there, whatever the training does. For
every listed view (training views of the split): the fraction of its rays that miss the dataparser's box, how
many of the object's pixels (DTU mask) are among them, and the fraction of the 20 left-most and right-most pixel
columns that miss (a strip along one edge is the box's side, not an unfitted field). The box is the dataparser's;
a run's log says whether fitting changed it ("the training views see all of the dataparser's box": unchanged).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "dtu" / "scan65")
    parser.add_argument("--views", type=int, nargs="+", default=[22, 25, 28])
    parser.add_argument("--edge", type=int, default=20, help="pixel columns counted as an image edge")
    args = parser.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from diagnose_views import object_mask  # the DTU image -> mask pairing the other diagnostics use

    from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
    from frugalnerf_ns.geometry.raymarch import intersect_aabb

    outputs = DTUDataParserConfig(data=args.data, train_views=tuple(args.views)).setup().get_dataparser_outputs("train")
    aabb = outputs.scene_box.aabb.float()
    print(f"box: {aabb[0].tolist()} .. {aabb[1].tolist()}")
    print("| view | rays missing the box | object pixels missing | left / right edge columns missing |")
    print("|---|---|---|---|")
    for index, name in enumerate(outputs.image_filenames):
        rays = outputs.cameras.generate_rays(camera_indices=index)
        height, width = rays.origins.shape[:2]
        hit = intersect_aabb(rays.origins.reshape(-1, 3).float(), rays.directions.reshape(-1, 3).float(), aabb).hit
        miss = ~hit.reshape(height, width)
        mask = object_mask(args.data / "mask", Path(name))
        if mask is None or mask.shape != miss.shape:
            raise SystemExit(f"box_coverage: error: no {height}x{width} mask for {name} in {args.data / 'mask'}")
        edge = args.edge
        print(f"| {Path(name).stem} | {float(miss.float().mean()):.3f} | {int((miss & mask).sum())} of {int(mask.sum())} | "
              f"{float(miss[:, :edge].float().mean()):.2f} / {float(miss[:, -edge:].float().mean()):.2f} |")


if __name__ == "__main__":
    main()
