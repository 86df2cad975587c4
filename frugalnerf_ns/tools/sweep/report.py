"""Tables and plots from sweep records: per scene and averaged (PSNR / SSIM / LPIPS / time), failures with
their logs, the Pareto plot of quality against training time and, for runs scored during training, the
anytime curves."""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any, Dict, List, Sequence

METRICS = ("psnr", "ssim", "lpips")


def _scene(r: Dict[str, Any]) -> str:
    return f"{r['scene']} ({r['views']}v)" if r.get("views") else r["scene"]


def _method(r: Dict[str, Any]) -> str:
    return r.get("label") or r["method"]


def scene_table(results: Sequence[Dict[str, Any]]) -> str:
    """One row per run, a mean row with the spread (max - min) where a method ran with several seeds, and an
    average over scenes per method that ran on every scene. Runs scored on a published shorter test list too
    (DTU: RegNeRF's 25 views beside pixelNeRF's 40) get those three metrics in extra columns."""
    results = [r for r in results if r.get("status", "ok") == "ok"]
    subsets = list(dict.fromkeys(k[: -len("_psnr")] for r in results for k in r if k.endswith("_psnr")))
    head = "| scene | method | PSNR | SSIM | LPIPS |" + "".join(f" PSNR / SSIM / LPIPS ({s}) |" for s in subsets)
    seeded = any(r.get("seed") is not None for r in results)
    head = head.replace("| method |", "| method | seed |") if seeded else head
    rows = [head + " train time | checkpoint MB | peak RSS MiB |", "|---" * (8 + len(subsets) + seeded) + "|"]

    def cells(r: Dict[str, Any]) -> str:
        text = f"{r['psnr']:.2f} | {r['ssim']:.3f} | {r.get('lpips', float('nan')):.3f} |"
        for subset in subsets:
            values = [r.get(f"{subset}_{k}") for k in METRICS]
            text += " " + (" / ".join(f"{v:.3f}" if v is not None else "-" for v in values)) + " |"
        return text

    methods = list(dict.fromkeys(_method(r) for r in results))
    scenes = list(dict.fromkeys(_scene(r) for r in results))
    for r in results:
        seed = f" {r.get('seed')} |" if seeded else ""
        rows.append(f"| {_scene(r)} | {_method(r)} |{seed} {cells(r)} {r['train_seconds'] / 60:.1f} min | "
                    f"{r.get('checkpoint_mb') or 0:.1f} | {r.get('peak_rss_mib') or 0:.0f} |")
    for scene in scenes:
        for m in methods:
            rs = [r for r in results if _scene(r) == scene and _method(r) == m]
            if seeded and len(rs) > 1:
                spread = {k: max(r[k] for r in rs) - min(r[k] for r in rs) for k in METRICS}
                mean = {k: statistics.fmean(r[k] for r in rs) for k in (*METRICS, "train_seconds")}
                rows.append(
                    f"| {scene} | {m} | mean of {len(rs)} (spread) | {mean['psnr']:.2f} ({spread['psnr']:.2f}) | "
                    f"{mean['ssim']:.3f} ({spread['ssim']:.3f}) | {mean['lpips']:.3f} ({spread['lpips']:.3f}) |"
                    + " |" * len(subsets) + f" {mean['train_seconds'] / 60:.1f} min | | |"
                )
    if len(scenes) > 1:
        for m in methods:
            rs = [r for r in results if _method(r) == m]
            if len({_scene(r) for r in rs}) == len(scenes):
                avg = {k: statistics.fmean(r.get(k) or 0 for r in rs) for k in (*METRICS, "train_seconds", "checkpoint_mb")}
                rows.append(
                    f"| average | {m} |" + (" all |" if seeded else "") + f" {avg['psnr']:.2f} | {avg['ssim']:.3f} | "
                    f"{avg['lpips']:.3f} |" + " |" * len(subsets) + f" {avg['train_seconds'] / 60:.1f} min | "
                    f"{avg['checkpoint_mb']:.1f} | |"
                )
    return "\n".join(rows)


def failure_table(records: Sequence[Dict[str, Any]]) -> str:
    failed = [r for r in records if r.get("status") == "failed"]
    if not failed:
        return ""
    lines = ["| scene | method | seed | stage | last error | log |", "|---|---|---|---|---|---|"]
    for r in failed:
        error = str(r.get("error", "")).replace("|", "\\|")
        lines.append(f"| {_scene(r)} | {_method(r)} | {r.get('seed')} | {r.get('stage', '')} | {error} | {r.get('log', '')} |")
    return "\n".join(lines)


def anytime_rows(records: Sequence[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """One row per scored checkpoint (runs with ``anytime``), else one per run at its end."""
    rows = []
    for r in records:
        if r.get("status", "ok") != "ok":
            continue
        points = r.get("anytime") or [{"step": None, "seconds": r["train_seconds"], **{k: r[k] for k in METRICS},
                                       "checkpoint_mb": r.get("checkpoint_mb")}]
        for point in points:
            rows.append({"run": (r.get("extra") or {}).get("run") or f"{_scene(r)} {_method(r)}", "method": r["method"],
                         "step": (point["step"] + 1) if point.get("step") is not None else None,
                         "seconds": point["seconds"], **{k: point[k] for k in METRICS},
                         "checkpoint_mb": point.get("checkpoint_mb"), "peak_rss_mib": r.get("peak_rss_mib"),
                         "run_dir": r.get("run_dir")})
    return rows


def pareto_front(points: List[Dict[str, Any]], key: str = "psnr", higher: bool = True) -> List[Dict[str, Any]]:
    """Points no other point beats on both wall time and ``key``, sorted by time."""
    front, best = [], None
    for point in sorted(points, key=lambda p: (p["seconds"], -p[key] if higher else p[key])):
        value = point[key] if higher else -point[key]
        if best is None or value > best:
            front.append(point)
            best = value
    return front


def anytime_table(rows: Sequence[Dict[str, Any]]) -> str:
    lines = ["| run | step | wall time | PSNR | SSIM | LPIPS | checkpoint MB | peak RSS MiB |", "|---" * 8 + "|"]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['step'] if r['step'] is not None else 'end'} | {r['seconds'] / 60:.1f} min | "
            f"{r['psnr']:.2f} | {r['ssim']:.3f} | {r['lpips']:.3f} | {r['checkpoint_mb'] or 0:.1f} | {r['peak_rss_mib'] or 0:.0f} |"
        )
    return "\n".join(lines)


def plot(rows: List[Dict[str, Any]], out: Path, anytime: bool = True) -> List[Path]:
    """``pareto.png`` (final PSNR and LPIPS against wall time, the Pareto front marked) and, where runs were
    scored during training, ``anytime.png`` (PSNR against wall time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    runs = list(dict.fromkeys(r["run"] for r in rows))
    finals = [max((r for r in rows if r["run"] == run), key=lambda r: r["seconds"]) for run in runs]
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for axis, key, higher, label in ((axes[0], "psnr", True, "test PSNR (dB)"), (axes[1], "lpips", False, "test LPIPS")):
        for point in finals:
            axis.scatter(point["seconds"] / 60, point[key], s=30)
            axis.annotate(point["run"], (point["seconds"] / 60, point[key]), fontsize=7, xytext=(3, 3),
                          textcoords="offset points")
        front = pareto_front(finals, key, higher)
        axis.step([p["seconds"] / 60 for p in front], [p[key] for p in front], where="post", color="black",
                  linewidth=1, label="Pareto front")
        axis.set_xlabel("wall-clock training time (min)")
        axis.set_ylabel(label)
        axis.legend(fontsize="small")
    figure.suptitle("Quality vs training time (final checkpoints)")
    figure.tight_layout()
    figure.savefig(out / "pareto.png", dpi=110)
    plt.close(figure)
    written.append(out / "pareto.png")

    if anytime and any(sum(1 for r in rows if r["run"] == run) > 1 for run in runs):
        figure, axis = plt.subplots(figsize=(7, 4.2))
        for run in runs:
            points = sorted((r for r in rows if r["run"] == run), key=lambda r: r["seconds"])
            axis.plot([p["seconds"] / 60 for p in points], [p["psnr"] for p in points], marker="o", markersize=3, label=run)
        axis.set_xlabel("wall-clock training time (min)")
        axis.set_ylabel("test PSNR (dB)")
        axis.set_title("Test PSNR during training (anytime curves)")
        axis.legend(fontsize="small")
        figure.tight_layout()
        figure.savefig(out / "anytime.png", dpi=110)
        plt.close(figure)
        written.append(out / "anytime.png")
    return written
