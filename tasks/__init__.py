"""Task registry, task implementations, expert training and demo data."""
from tasks.core import Task, make_task
from tasks.registry import TASKS, TaskSpec, UnknownTaskError, get_spec, register

__all__ = ["TASKS", "Task", "TaskSpec", "UnknownTaskError", "get_spec", "make_task", "register"]
