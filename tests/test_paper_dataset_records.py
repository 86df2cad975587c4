"""The results tables' rows for the paper's other datasets (fortress, the RealEstate-10K clips) and nerfacto's cells show
the numbers of their committed record (docs/notes/paper_datasets/rows.json), on the README and on docs/results.md."""

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RECORD = json.loads((ROOT / "docs" / "notes" / "paper_datasets" / "rows.json").read_text())
TRIPLE = re.compile(r"(\d+\.\d\d) / (0\.\d\d\d) / (0\.\d\d\d)")
# How the pages name the scenes whose rows come from this record (first match wins).
SCENES = {"RealEstate-10K 5aca": "re10k_5aca", "RealEstate-10K 3222": "re10k_3222", "RealEstate-10K ffa9": "re10k_ffa9",
          "fortress": "fortress"}


def shown(run):
    return (f"{run['psnr']:.2f}", f"{run['ssim']:.3f}", f"{run['lpips']:.3f}")


def recorded(scene, views, method):
    return {shown(run) for run in RECORD["runs"] if (run["scene"], run["views"], run["method"]) == (scene, views, method)}


def rows(page):
    """(scene, views, triples) of every table row of ``page`` naming a scene of ``SCENES``: the PSNR / SSIM / LPIPS
    triples of its cells before the last (the paper's own numbers), in column order (ours, tensorf, nerfacto)."""
    found = []
    for line in (ROOT / page).read_text().splitlines():
        if not line.startswith("| "):
            continue
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        scene = next((key for name, key in SCENES.items() if name in cells[0]), None)
        if scene is not None:
            found.append((scene, int(cells[1]), [m.groups() for m in map(TRIPLE.search, cells[:-1]) if m]))
    return found


@pytest.mark.parametrize("page", ["README.md", "docs/results.md"])
def test_every_row_of_these_scenes_shows_recorded_numbers(page):
    found = rows(page)
    assert {scene for scene, *_ in found} == set(SCENES.values()), page
    for scene, views, triples in found:
        assert triples, (page, scene, views)
        for triple, method in zip(triples, ["frugalnerf-cpu", "tensorf", "nerfacto"]):
            assert triple in recorded(scene, views, method), (page, scene, views, method, triple)


def test_the_fern_nerfacto_cell_is_the_record():
    text = (ROOT / "docs" / "results.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| fern | 2 |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    header = next(line for line in text.splitlines() if line.startswith("| scene | views | resolution | ours"))
    column = [cell.strip() for cell in header.strip("|").split("|")].index("nerfstudio nerfacto")
    assert TRIPLE.search(cells[column]).groups() in recorded("fern", 2, "nerfacto")


def test_a_changed_number_fails():
    (run,) = [r for r in RECORD["runs"] if (r["scene"], r["method"]) == ("fortress", "frugalnerf-cpu")]
    edited = (f"{run['psnr'] + 0.01:.2f}", f"{run['ssim']:.3f}", f"{run['lpips']:.3f}")
    assert edited not in recorded("fortress", 2, "frugalnerf-cpu")
