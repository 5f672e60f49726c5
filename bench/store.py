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


class Store:
    def __init__(self, root: str = DEFAULT_ROOT):
        self.root = root

    def path(self, run_id: str) -> str:
        return os.path.join(self.root, f"{run_id}.json")

    def get(self, run_id: str) -> dict | None:
        try:
            with open(self.path(run_id)) as f:
                return json.load(f)
        except FileNotFoundError:
            return None

    def finished(self, run_id: str) -> dict | None:
        rec = self.get(run_id)
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
