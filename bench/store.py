"""Results store: one JSON file per run in a local directory (the embedded default).

Writes are atomic (temp file in the same directory, fsync, os.replace), so a killed run or
a crashed writer never leaves a half-written or corrupted record, and concurrent writers of
different runs never touch the same file. Run ids are content hashes, so a finished cell is
found by name and skipped.
"""
from __future__ import annotations

import json
import os
import tempfile
import warnings
from typing import IO, Callable, Iterator

DEFAULT_ROOT = os.environ.get("ILDBENCH_STORE", "runs")
FINISHED = ("ok", "diverged")


def write_atomic(path: str, write: Callable[[IO], None], binary: bool = False) -> None:
    """Write a file so that readers see the old file or the new one, never a partial one:
    `write(f)` into a temp file in the same directory, fsync, os.replace."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-",
                               suffix=os.path.splitext(path)[1])
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json_atomic(path: str, obj) -> None:
    write_atomic(path, lambda f: json.dump(obj, f, indent=1, sort_keys=True, allow_nan=True))


class CorruptRecord(ValueError):
    """A record file that is not a JSON object (truncated by a full disk or a copy cut short,
    or hand-edited); the message names the file and the fix."""


class Store:
    def __init__(self, root: str = DEFAULT_ROOT):
        self.root = root

    def path(self, run_id: str) -> str:
        return os.path.join(self.root, f"{run_id}.json")

    def get(self, run_id: str) -> dict | None:
        """The record of `run_id`, None if there is none; CorruptRecord if its file cannot
        be read as a record."""
        path = self.path(run_id)
        try:
            with open(path) as f:
                rec = json.load(f)
        except FileNotFoundError:
            return None
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CorruptRecord(f"record {path} is not valid JSON ({e}): it was truncated or "
                                "edited by hand; delete it (or run the sweep again, which "
                                "sets it aside under corrupt/ and re-runs the cell)") from e
        if not isinstance(rec, dict):
            raise CorruptRecord(f"record {path} holds a {type(rec).__name__}, not a run "
                                "record; delete it and re-run the cell")
        return rec

    def finished(self, run_id: str) -> dict | None:
        """The finished record of `run_id`, or None: the cell is to be run. A corrupt record
        file is moved to <store>/corrupt/ (kept, not deleted: a later one of the same cell
        becomes <id>.2.json, and so on) with a warning naming it, and its cell then counts as
        not run."""
        try:
            rec = self.get(run_id)
        except CorruptRecord as e:
            aside = os.path.join(self.root, "corrupt")
            os.makedirs(aside, exist_ok=True)
            dest, n = os.path.join(aside, f"{run_id}.json"), 1
            while os.path.exists(dest):  # an earlier corrupt copy of this cell is kept too
                n += 1
                dest = os.path.join(aside, f"{run_id}.{n}.json")
            os.replace(self.path(run_id), dest)
            warnings.warn(f"{e}; moved to {dest}, and the cell re-runs")
            return None
        return rec if rec is not None and rec.get("status") in FINISHED else None

    def write(self, record: dict) -> str:
        path = self.path(record["run_id"])
        write_json_atomic(path, record)
        return path

    def trajectory_path(self, run_id: str) -> str:
        return os.path.join(self.root, f"{run_id}.traj.npz")

    def write_trajectory(self, run_id: str, states) -> str:
        """The final policy's first evaluation episode, as matched states (T+1, S) float32
        (for renders); written atomically beside the record."""
        import numpy as np
        path = self.trajectory_path(run_id)
        write_atomic(path, lambda f: np.savez_compressed(
            f, states=np.asarray(states, np.float32)), binary=True)
        return path

    def trajectory(self, run_id: str):
        import numpy as np
        try:
            with np.load(self.trajectory_path(run_id)) as z:
                return z["states"]
        except FileNotFoundError:
            return None

    def checkpoint_path(self, run_id: str) -> str:
        """Where a run with an env-step budget keeps the state it resumes from after a stop
        (`RunContext.checkpoint`); removed once the run's record is written."""
        return os.path.join(self.root, "checkpoints", f"{run_id}.pkl")

    def records(self) -> Iterator[dict]:
        if not os.path.isdir(self.root):
            return
        for name in sorted(os.listdir(self.root)):
            if not name.endswith(".json") or name.startswith("."):
                continue
            try:
                with open(os.path.join(self.root, name)) as f:
                    yield json.load(f)
            except (OSError, json.JSONDecodeError) as e:  # hand-edited or foreign file
                warnings.warn(f"skipping unreadable record {name}: {e}")
