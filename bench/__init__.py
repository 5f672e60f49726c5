"""ildbench harness: budgets, runner, evaluator, results store, reports, CLI."""
__version__ = "0.1.0"  # the package version (pyproject reads it here); hashed into run ids
