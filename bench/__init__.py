"""ildbench harness: budgets, runner, evaluator, results store, reports, CLI."""
__version__ = "0.1.0"


def _quiet_third_party() -> None:
    """Keep two libraries' import-time noise out of every run's output: mujoco's MJX prints
    "Failed to import warp" when the optional warp package is absent (brax's own pipelines,
    which ildbench uses, do not need it), and brax warns on import that it is not actively
    maintained. Both are said once, here, rather than in every run and every spawned cell."""
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
