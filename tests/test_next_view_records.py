"""The next-view study's pages show the numbers of its committed records: the rank check's table (experiment notes)
and the sentence about it on the results page."""

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RANK = json.loads((ROOT / "docs" / "notes" / "next_view" / "rank_check.json").read_text())


def test_the_rank_table_in_the_notes_is_the_record():
    text = (ROOT / "docs" / "notes" / "next-view.md").read_text()
    rows = re.findall(r"^\| (\w+) \| (\w+)[^|]* \| (\d+) \| ([\d.]+) \| ([\d.]+) \|$", text, flags=re.M)
    assert len(rows) == sum(len(split["runs"]) for split in RANK["splits"].values()) == 4
    for split, rule, frame, short, long in rows:
        run = RANK["splits"][split]["runs"][rule]
        assert int(frame) == run["frame"]
        assert float(short) == round(run[f"i{RANK['short']}"], 2) and float(long) == round(run[f"i{RANK['long']}"], 2)


def test_the_results_page_quotes_the_record():
    text = " ".join((ROOT / "docs" / "results.md").read_text().split())
    sentence = text.split("was checked on two splits")[1].split("rank_check.json")[0]
    quoted = [float(x) for x in re.findall(r"\d+\.\d\d", sentence)]
    record = {round(run[f"i{RANK['long']}"], 2) for split in RANK["splits"].values() for run in split["runs"].values()}
    assert len(quoted) == 4 and set(quoted) <= record
    assert all(split["same_order"] for split in RANK["splits"].values()) and "order them alike" in sentence
