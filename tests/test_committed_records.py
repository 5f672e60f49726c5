"""Every committed record can be found again: its file is named by its run id, and for the
registered version of its method the id recomputed from its content is that id. A field
added to `Budget`, `EvalConfig` or a method config without a default that keeps the old
behaviour would re-key these records silently; this test names them instead."""
from __future__ import annotations

import glob
import json
import os

import pytest

from bench.plugins import all_methods
from bench.runner import record_run_id

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def committed_records() -> list[tuple[str, dict]]:
    out = []
    for path in sorted(glob.glob(os.path.join(ROOT, "results", "**", "*.json"), recursive=True)):
        if os.sep + "runs" not in path:  # records live in a store: .../runs/<id>.json
            continue
        with open(path) as f:
            rec = json.load(f)
        if isinstance(rec, dict) and "run_id" in rec and "method" in rec:
            out.append((os.path.relpath(path, ROOT), rec))
    return out


RECORDS = committed_records()


def test_the_committed_stores_hold_records():
    assert len(RECORDS) > 500
    assert {p.split(os.sep)[1] for p, _ in RECORDS} >= {"grid", "tenmin", "gpu", "steps200k"}


def test_every_record_file_is_named_by_its_run_id():
    bad = [p for p, r in RECORDS if os.path.basename(p) != r["run_id"] + ".json"]
    assert bad == []


def test_every_current_version_record_recomputes_to_its_run_id():
    """Records of an older method version (cells waiting to be re-run, listed in
    CHANGELOG.md) were keyed with that version's config defaults, which the registry no
    longer holds; every other record must recompute exactly."""
    methods = all_methods()
    current = [(p, r) for p, r in RECORDS
               if r["method"] in methods and r.get("method_version") == methods[r["method"]].version]
    assert len(current) > 300
    bad = [(p, record_run_id(r)) for p, r in current if record_run_id(r) != r["run_id"]]
    assert bad == []


def test_a_changed_record_no_longer_matches_its_id():
    """The check can fail: one field of a record's budget changed gives another id."""
    methods = all_methods()
    p, r = next((p, r) for p, r in RECORDS if r["method"] == "bc"
                and r.get("method_version") == methods["bc"].version)
    changed = json.loads(json.dumps(r))
    changed["seed"] = r["seed"] + 1000
    assert record_run_id(changed) != r["run_id"]
