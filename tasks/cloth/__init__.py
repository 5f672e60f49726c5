"""The cloth-hanging task (paper Section 4.2): tasks/cloth/sim.py (the simulator) and
tasks/cloth/env.py (the task as a brax Env)."""
