"""The results file of a sweep: one JSON record per finished run, appended as it finishes.

Appending one line per run (flushed and fsynced) means a sweep killed at any point keeps every run that
finished; a torn last line (killed mid-write) is skipped when read. A run is done when it has a record with
status "ok"; a run that failed is tried again by the next invocation, once: after two failed records it is
reported, not re-run (``retry_failed`` re-runs it anyway).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Dict, Iterable, List

MAX_ATTEMPTS = 2


class ResultStore:
    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def records(self) -> List[Dict[str, Any]]:
        if not self.path.exists():
            return []
        out = []
        for line in self.path.read_text().splitlines():
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by a kill mid-write
            if isinstance(record, dict) and "key" in record:
                out.append(record)
        return out

    def append(self, record: Dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        torn = False
        if self.path.exists() and self.path.stat().st_size:
            with open(self.path, "rb") as existing:
                existing.seek(-1, os.SEEK_END)
                torn = existing.read(1) != b"\n"  # the last write was cut: start a fresh line
        with open(self.path, "a") as handle:
            handle.write(("\n" if torn else "") + json.dumps(record, default=str) + "\n")
            handle.flush()
            os.fsync(handle.fileno())

    def latest(self, keys: Iterable[str]) -> Dict[str, Dict[str, Any]]:
        """key -> its ok record (the last one), or else its last failed record."""
        wanted, chosen = set(keys), {}
        for record in self.records():
            key = record["key"]
            if key not in wanted:
                continue
            if record.get("status") == "ok" or chosen.get(key, {}).get("status") != "ok":
                chosen[key] = record
        return chosen

    def to_run(self, keys: Iterable[str], retry_failed: bool = False) -> List[str]:
        """Keys without an ok record and with fewer than MAX_ATTEMPTS failures (all failures with retry_failed)."""
        done, failures = set(), {}
        for record in self.records():
            if record.get("status") == "ok":
                done.add(record["key"])
            else:
                failures[record["key"]] = failures.get(record["key"], 0) + 1
        return [k for k in keys if k not in done and (retry_failed or failures.get(k, 0) < MAX_ATTEMPTS)]
