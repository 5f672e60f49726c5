"""Fast differentiable physics: exact-equivalent rewrites of brax's step and each task's plan
of them (`plan`). One module per rewrite; `transforms` applies them to a task."""
from tasks.physics.plan import CHOICES, PLANS, REFERENCE, Plan, apply, choose, plan_for

__all__ = ["CHOICES", "PLANS", "REFERENCE", "Plan", "apply", "choose", "plan_for"]
