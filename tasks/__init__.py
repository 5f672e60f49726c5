"""Task registry, task implementations, differentiable physics and demo data."""


def _quiet_third_party() -> None:
    """Keep two libraries' import-time noise out of every run's output: mujoco's MJX prints
    "Failed to import warp" when the optional warp package is absent (brax's own pipelines,
    which the tasks use, do not need it), and brax warns on import that it is not actively
    maintained. Run here, before this package's first brax import, so it costs nothing a
    process that steps a task would not pay anyway."""
    import contextlib
    import io
    import warnings
    warnings.filterwarnings("ignore", message="Brax System, piplines", category=UserWarning)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            import mujoco.mjx.warp  # noqa: F401  (the print happens at its import)
    except Exception:  # mujoco absent or broken: brax's import reports that itself
        pass


_quiet_third_party()

from tasks.core import Task, make_task  # noqa: E402
from tasks.registry import TASKS, TaskSpec, UnknownTaskError, get_spec, register  # noqa: E402

__all__ = ["TASKS", "Task", "TaskSpec", "UnknownTaskError", "get_spec", "make_task", "register"]
