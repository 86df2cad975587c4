"""Which next photo helps most: the suggestion against the largest-gap rule and random frames, on the captures.

    python scripts/next_view_study.py plan                 # the splits, test frames and rule picks (no results used)
    python scripts/next_view_study.py run [--iterations N] # trains every planned run not yet done, one at a time
    python scripts/next_view_study.py table                # the table of every run (Markdown) and its JSON record
    python scripts/next_view_study.py run --iterations 1500 --picks-from i750 --only S --rules R ...  # the same picks, longer
    python scripts/next_view_study.py rank --iterations 1500 --picks-from i750    # do both lengths rank the rules alike?

Protocol (fixed before any result was looked at): per capture, the frames in azimuth order around the focus of all
its cameras; every ``TEST_EVERY``-th of them is a test frame, used by no run for training. Each starting split holds
k photos; the next photo is (a) ``frugalnerf-next-view``'s first suggestion on the run trained with the k photos,
snapped to the nearest capture frame, (b) the frame nearest the middle of the largest azimuth gap between the photos
that holds a frame, (c) two random frames (seeded by the split's name). Each k+1 split trains ``frugalnerf-cpu`` and
is scored on the test frames with the project's evaluator.
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List

import torch

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "captures"
RUNS = ROOT / "outputs" / "next_view_study"
PLAN = ROOT / "docs" / "notes" / "next_view" / "plan.json"
RECORD = ROOT / "docs" / "notes" / "next_view" / "study.json"
SUGGESTIONS = ROOT / "docs" / "notes" / "next_view" / "suggestions.json"
TEST_EVERY = {"juice_box": 8, "bird": 12}
NEAR_FRAME = 1.0
"""A suggestion whose nearest pool frame stands farther than this (the data's units) has no frame to stand in for it
(the juice box's capture covers 82 degrees of the table; a suggestion on its far side snaps 10-13 units away)."""
# Starting splits as target azimuths (degrees around the focus of all frames; the juice box's frames span 0-82,
# the bird's the whole circle): a pair at one end, a pair across the arc, three photos; the bird's gate split
# (frames 0 23 46), a close pair, three photos 120 degrees apart.
STARTS = {
    "juice_box": {"jb_end_pair": [5, 30], "jb_wide_pair": [10, 75], "jb_three": [20, 40, 55]},
    "bird": {"bird_gate3": [0, 32, 78], "bird_pair": [0, 47], "bird_three_120": [0, 120, -120]},
}


def frame_azimuths(scene: str) -> torch.Tensor:
    """Each frame's azimuth (degrees) around the focus of all the capture's cameras (least squares with the default
    ridge), about their mean up, 0 at the first frame: the frame the plan was made in (kept here as it was, so the
    committed plan and table reproduce)."""
    from frugalnerf_ns.data.dataparsers.llff import load_poses_bounds
    from frugalnerf_ns.geometry.camera_conventions import llff_to_opengl
    from frugalnerf_ns.geometry.scene_analysis import focus_point
    from frugalnerf_ns.geometry.viewpoints import SubjectFrame

    poses, _ = load_poses_bounds(DATA / scene / "poses_bounds.npy")
    c2w = torch.from_numpy(llff_to_opengl(poses[:, :, :4])).double()
    focus = focus_point(c2w)
    up = torch.nn.functional.normalize(c2w[:, :3, 1].mean(0), dim=0)
    first = c2w[0, :3, 3] - focus
    first = first - (first @ up) * up
    return SubjectFrame(focus, up, first / first.norm()).azimuths(c2w[:, :3, 3])


def angular(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def largest_gap_frame(azimuths: torch.Tensor, photos: List[int], pool: List[int]) -> int:
    """The pool frame nearest the middle of the largest azimuth gap between neighbouring photos that holds a pool frame."""
    angles = sorted((float(azimuths[p]) % 360.0, p) for p in photos)
    best = None
    for i, (start, _) in enumerate(angles):
        end = angles[(i + 1) % len(angles)][0] + (360.0 if i + 1 == len(angles) else 0.0)
        inside = [f for f in pool if 0 < (float(azimuths[f]) % 360.0 - start) % 360.0 < end - start]
        if inside and (best is None or end - start > best[0]):
            middle = (start + end) / 2.0
            best = (end - start, min(inside, key=lambda f: angular(float(azimuths[f]), middle)))
    assert best is not None, "no pool frame between the photos"
    return best[1]


def plan() -> Dict:
    splits = {}
    for scene, starts in STARTS.items():
        azimuths = frame_azimuths(scene)
        order = azimuths.argsort().tolist()
        test = sorted(order[:: TEST_EVERY[scene]])
        for name, targets in starts.items():
            free = [f for f in range(len(azimuths)) if f not in test]
            photos = [min(free, key=lambda f: angular(float(azimuths[f]), t)) for t in targets]
            pool = [f for f in free if f not in photos]
            draws = random.Random(name).sample(pool, 2)
            splits[name] = {
                "scene": scene, "photos": photos, "test": test, "pool_size": len(pool),
                "photo_azimuths": [round(float(azimuths[p]), 1) for p in photos],
                "picks": {"gap": largest_gap_frame(azimuths, photos, pool), "random1": draws[0], "random2": draws[1]},
            }
    return {"protocol": __doc__.split("Protocol")[1].strip(), "splits": splits}


def run_minutes(out: Path) -> float:
    """Training minutes of a run: from its config.yml (written at start) to its last checkpoint."""
    config = next(out.rglob("config.yml"))
    last = max(out.rglob("step-*.ckpt"), key=lambda path: path.stat().st_mtime)
    return (last.stat().st_mtime - config.stat().st_mtime) / 60.0


def train(name: str, scene: str, views: List[int], test: List[int], iterations: int, seed: int = 42) -> Path:
    """Trains (unless its last checkpoint exists) and scores one run; returns its folder."""
    out = RUNS / name
    if (out / "scores.json").is_file():
        return out
    out.mkdir(parents=True, exist_ok=True)
    tools = [sys.executable, "-m", "frugalnerf_ns.tools.offline_tools"]
    while subprocess.run(["pgrep", "-f", "offline_tools train"], capture_output=True).returncode == 0:
        time.sleep(10)  # one training at a time (a queue restarted while its last run still trains)
    if not list(out.rglob(f"step-{iterations - 1:09d}.ckpt")):
        with open(out / "train.log", "w") as log:
            subprocess.run(tools + ["train", "frugalnerf-cpu", "--data", str(DATA / scene), "--output-dir", str(out),
                                    "--vis", "tensorboard", "--machine.seed", str(seed), "--pipeline.datamanager.seed",
                                    str(seed), "--max-num-iterations", str(iterations), "frugal-llff", "--train-views",
                                    *map(str, views), "--test-views", *map(str, test)],
                           stdout=log, stderr=subprocess.STDOUT, check=True, cwd=ROOT)
    config = next(out.rglob("config.yml"))
    result = subprocess.run(tools + ["eval", str(config)], capture_output=True, text=True, check=True, cwd=ROOT)
    scores = json.loads(result.stdout.split("RESULT ")[-1])
    (out / "scores.json").write_text(json.dumps({"train_minutes": run_minutes(out), "config": str(config.relative_to(ROOT)),
                                                 "views": views, **scores}, indent=1))
    return out


def frame_centres(scene: str) -> torch.Tensor:
    """Every frame's camera centre in the data's own frame (poses_bounds.npy)."""
    from frugalnerf_ns.data.dataparsers.llff import load_poses_bounds

    poses, _ = load_poses_bounds(DATA / scene / "poses_bounds.npy")
    return torch.from_numpy(poses[:, :, 3]).double()


def suggest(run: Path, split: Dict, tool_root: Path) -> Dict:
    """``frugalnerf-next-view`` on the k-photo run (the tool of ``tool_root``'s tree), each suggestion snapped to the
    pool frame whose camera centre is nearest."""
    config = next(run.rglob("config.yml"))
    result = subprocess.run([sys.executable, "-m", "frugalnerf_ns.tools.next_view", "--load-config", str(config),
                             "--no-viewer-copy"], capture_output=True, text=True, cwd=tool_root)
    if result.returncode != 0:
        raise SystemExit(f"next-view failed on {config}:\n{result.stdout[-2000:]}\n{result.stderr[-3000:]}")
    record = json.loads((config.parent / "next_view.json").read_text())
    centres = frame_centres(split["scene"])
    pool = [f for f in range(len(centres)) if f not in split["test"] and f not in split["photos"]]
    snapped = []
    for suggestion in record["suggestions"]:
        position = torch.tensor(suggestion["camera_to_world_data_frame"], dtype=torch.float64)[:3, 3]
        distance = (centres[pool] - position).norm(dim=-1)
        snapped.append({"frame": pool[int(distance.argmin())], "distance": float(distance.min()),
                        "description": suggestion["description"], "score": suggestion["score"]})
    return {"seconds": record["seconds"], "score": record["score"], "snapped": snapped}


def table(study: Dict, tag: str) -> None:
    """Every finished run as a Markdown table per split, the means over the finished splits, and the record."""
    suggestions = json.loads(SUGGESTIONS.read_text()) if SUGGESTIONS.is_file() else {}
    record = {"protocol": study["protocol"], "iterations": int(tag[1:]), "preset": "frugalnerf-cpu", "seed": 42,
              "machine": "2-core AMD EPYC (AVX-512), torch 2.14.1", "evaluator":
              "python -m frugalnerf_ns.tools.offline_tools eval <run>/config.yml", "splits": {}}
    lines = ["| split | photos (azimuth) | rule | next frame (azimuth) | test PSNR / SSIM / LPIPS | train min |",
             "|---|---|---|---|---|---|"]
    gains = {"random": [], "gap": []}
    near = {"random": [], "gap": []}  # splits whose capture holds a frame where the suggestion stands
    by_score: Dict[str, Dict[str, List[float]]] = {}  # the scores the splits were first suggested with
    for name, split in study["splits"].items():
        key = f"{tag}/{name}"
        if key not in suggestions:
            continue
        azimuths = frame_azimuths(split["scene"])
        suggestion = suggestions[key]
        picks = {"suggestion": suggestion["snapped"][0]["frame"], **split["picks"]}
        if "earlier" in suggestion:  # the score the tool defaulted to before: its pick, kept for the record
            picks["earlier suggestion"] = suggestion["earlier"]["snapped"][0]["frame"]
        runs = {"k photos": RUNS / tag / name / "k"} | {rule: RUNS / tag / name / f"frame{f}" for rule, f in picks.items()}
        scores = {rule: json.loads((run / "scores.json").read_text()) for rule, run in runs.items()
                  if (run / "scores.json").is_file()}
        photos = ", ".join(f"{p} ({float(azimuths[p]):.0f})" for p in split["photos"])
        for rule, score in scores.items():
            frame = picks.get(rule)
            where = "-" if frame is None else f"{frame} ({float(azimuths[frame]):.0f})"
            label = {"suggestion": f"suggestion ({suggestion['score']})",
                     "earlier suggestion": f"suggestion ({suggestion.get('earlier', {}).get('score')})"}.get(rule, rule)
            lines.append(f"| {name} | {photos} | {label} | {where} | {score['psnr']:.2f} / {score['ssim']:.3f} / "
                         f"{score['lpips']:.3f} | {score['train_minutes']:.1f} |")
        record["splits"][name] = {"scene": split["scene"], "photos": split["photos"], "test": split["test"],
                                  "picks": picks, "suggestion": suggestions[key],
                                  "runs": {rule: {k: score[k] for k in ("psnr", "ssim", "lpips", "train_minutes", "views")}
                                           for rule, score in scores.items()}}
        if all(rule in scores for rule in ("suggestion", "gap", "random1", "random2")):
            random_psnr = (scores["random1"]["psnr"] + scores["random2"]["psnr"]) / 2.0
            gains["random"].append(scores["suggestion"]["psnr"] - random_psnr)
            gains["gap"].append(scores["suggestion"]["psnr"] - scores["gap"]["psnr"])
            if suggestion["snapped"][0]["distance"] <= NEAR_FRAME:
                near["random"].append(gains["random"][-1])
                near["gap"].append(gains["gap"][-1])
            first = "earlier suggestion" if "earlier suggestion" in scores else "suggestion"
            first_score = suggestion.get("earlier", suggestion)["score"]
            by_score.setdefault(first_score, {"random": [], "gap": []})
            by_score[first_score]["random"].append(scores[first]["psnr"] - random_psnr)
            by_score[first_score]["gap"].append(scores[first]["psnr"] - scores["gap"]["psnr"])
    record["mean_gain_db"] = {rule: (sum(v) / len(v) if v else None) for rule, v in gains.items()}
    record["complete_splits"] = len(gains["gap"])
    record["near_frame"] = {"max_distance": NEAR_FRAME, "splits": len(near["gap"]),
                            "mean_gain_db": {rule: (sum(v) / len(v) if v else None) for rule, v in near.items()}}
    record["first_suggested_with"] = {score: {rule: sum(v) / len(v) for rule, v in g.items()} | {"splits": len(g["gap"])}
                                      for score, g in by_score.items()}
    RECORD.write_text(json.dumps(record, indent=1) + "\n")
    print("\n".join(lines))
    print(f"\nover {len(gains['gap'])} complete splits: suggestion - random (mean of 2 draws) "
          f"{record['mean_gain_db']['random']} dB, suggestion - largest gap {record['mean_gain_db']['gap']} dB")
    print(f"where a frame stands within {NEAR_FRAME} of the suggestion ({len(near['gap'])} splits): "
          f"- random {record['near_frame']['mean_gain_db']['random']} dB, - gap {record['near_frame']['mean_gain_db']['gap']} dB")
    for score, g in record["first_suggested_with"].items():
        print(f"first suggested with {score} ({g['splits']} splits): - random {g['random']:.2f} dB, - gap {g['gap']:.2f} dB")


RANK_RECORD = ROOT / "docs" / "notes" / "next_view" / "rank_check.json"


def rank_check(study: Dict, short: str, long: str) -> None:
    """The same rules' frames trained at two lengths: each run's test PSNR and the order of the rules at each."""
    suggestions = json.loads(SUGGESTIONS.read_text())
    lines = [f"| split | rule | frame | PSNR at {short[1:]} steps | PSNR at {long[1:]} steps |", "|---|---|---|---|---|"]
    record: Dict = {"short": int(short[1:]), "long": int(long[1:]), "preset": "frugalnerf-cpu", "seed": 42, "splits": {}}
    for name, split in study["splits"].items():
        key = f"{short}/{name}"
        if key not in suggestions:
            continue
        picks = {"suggestion": suggestions[key]["snapped"][0]["frame"], **split["picks"]}
        if "earlier" in suggestions[key]:
            picks["earlier"] = suggestions[key]["earlier"]["snapped"][0]["frame"]
        rows = {}
        # The shorter study's scores from its run folders, else from its committed record (a fresh checkout).
        recorded = json.loads(RECORD.read_text())["splits"].get(name, {}) if RECORD.is_file() else {}
        by_frame = {f"frame{recorded['picks'][r]}": run["psnr"] for r, run in recorded.get("runs", {}).items()
                    if r in recorded.get("picks", {})}
        for rule, frame in picks.items():
            short_file, long_file = (RUNS / tag / name / f"frame{frame}" / "scores.json" for tag in (short, long))
            short_psnr = json.loads(short_file.read_text())["psnr"] if short_file.is_file() else by_frame.get(f"frame{frame}")
            if short_psnr is not None and long_file.is_file():
                rows[rule] = {"frame": frame, short: short_psnr, long: json.loads(long_file.read_text())["psnr"]}
        if len(rows) < 2:
            continue
        order = {tag: sorted(rows, key=lambda rule: -rows[rule][tag]) for tag in (short, long)}
        record["splits"][name] = {"runs": rows, "order": order, "same_order": order[short] == order[long]}
        for rule, row in rows.items():
            lines.append(f"| {name} | {rule} | {row['frame']} | {row[short]:.2f} | {row[long]:.2f} |")
        lines.append(f"| {name} | order | | {' > '.join(order[short])} | {' > '.join(order[long])} |")
    RANK_RECORD.write_text(json.dumps(record, indent=1) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("command", choices=["plan", "run", "table", "rank"])
    parser.add_argument("--iterations", type=int, default=750)
    parser.add_argument("--force", action="store_true", help="plan: overwrite the existing plan")
    parser.add_argument("--only", nargs="*", default=None, help="split names to run, in this order")
    parser.add_argument("--resuggest", action="store_true",
                        help="run: ask the tool again on splits suggested with a score that is no longer its default")
    parser.add_argument("--picks-from", default=None, help="run: train the frames the rules picked in this study "
                        "(e.g. i750) at --iterations, without a k-photo run or a new suggestion")
    parser.add_argument("--rules", nargs="*", default=None, help="run with --picks-from: only these rules' frames "
                        "(suggestion, gap, random1, random2, earlier: the suggestion of the score that was the default before)")
    parser.add_argument("--tool-root", type=Path, default=ROOT, help="source tree whose frugalnerf-next-view suggests")
    args = parser.parse_args()
    if args.command == "plan":
        if PLAN.is_file() and not args.force:
            sys.exit(f"{PLAN} exists: the plan is fixed before any training (--force writes a new one)")
        PLAN.parent.mkdir(parents=True, exist_ok=True)
        PLAN.write_text(json.dumps(plan(), indent=1) + "\n")
        print(PLAN.read_text())
        return
    study = json.loads(PLAN.read_text())
    if args.command == "table":
        table(study, f"i{args.iterations}")
        return
    if args.command == "rank":  # --picks-from the shorter study, --iterations the longer
        rank_check(study, args.picks_from or "i750", f"i{args.iterations}")
        return
    if args.command == "run":
        tag = f"i{args.iterations}"
        suggestions = json.loads(SUGGESTIONS.read_text()) if SUGGESTIONS.is_file() else {}
        for name in args.only or list(study["splits"]):
            split = study["splits"][name]
            if args.picks_from:
                # The rules' frames as the shorter study picked them, trained longer: does the length of training
                # change how the same picks rank?
                recorded = suggestions[f"{args.picks_from}/{name}"]
                picks = {"suggestion": recorded["snapped"][0]["frame"], **split["picks"]}
                if "earlier" in recorded:
                    picks["earlier"] = recorded["earlier"]["snapped"][0]["frame"]
                for rule in args.rules or list(picks):
                    train(f"{tag}/{name}/frame{picks[rule]}", split["scene"], split["photos"] + [picks[rule]],
                          split["test"], args.iterations)
                print(name, "done", flush=True)
                continue
            base = train(f"{tag}/{name}/k", split["scene"], split["photos"], split["test"], args.iterations)
            key = f"{tag}/{name}"
            if key not in suggestions:
                suggestions[key] = suggest(base, split, args.tool_root)
                SUGGESTIONS.write_text(json.dumps(suggestions, indent=1) + "\n")
            elif args.resuggest:
                # The tool's default score changed after this split's suggestion was recorded: ask again, keep the
                # earlier suggestion (and its run) beside it in the record.
                current = suggest(base, split, args.tool_root)
                if current["score"] != suggestions[key]["score"]:
                    earlier = {k: v for k, v in suggestions[key].items() if k != "earlier"}
                    suggestions[key] = {**current, "earlier": earlier}
                    SUGGESTIONS.write_text(json.dumps(suggestions, indent=1) + "\n")
            picks = {"suggestion": suggestions[key]["snapped"][0]["frame"], **split["picks"]}
            for rule, frame in picks.items():
                train(f"{tag}/{name}/frame{frame}", split["scene"], split["photos"] + [frame], split["test"], args.iterations)
            print(name, "done", flush=True)


if __name__ == "__main__":
    main()
