"""ildbench harness: budgets, runner, evaluator, results store, reports, CLI."""
__version__ = "0.1.0"
