"""cem_mpc: receding-horizon CEM in the simulator at test time (a reference, ILD paper A.3).

Two registered methods share the planner, one per objective, so that each declares exactly
what it reads: `cem_mpc` (true reward; the paper's reference) and `cem_mpc_track` (tracks the
demo's matched states; no reward)."""
from bench.api import MethodSpec, Uses
from methods.cem_mpc.config import PRESETS, CEMConfig, CEMTrackConfig
from methods.cem_mpc.train import make_train

METHOD = MethodSpec(
    name="cem_mpc",
    train=make_train("reward"),
    config_cls=CEMConfig,
    uses=Uses(true_reward=True, sim_at_test=True),
    description="reference: CEM planning on the true reward with the simulator and full "
                "state at test time",
    presets=PRESETS,
    reference=True,
)

TRACK = MethodSpec(
    name="cem_mpc_track",
    train=make_train("track"),
    config_cls=CEMTrackConfig,
    uses=Uses(demo_states=True, sim_at_test=True),
    description="reference: CEM planning that tracks the demo's states with the simulator and "
                "full state at test time (no reward)",
    presets=PRESETS,
    reference=True,
    version="2",  # 2: the tracking cost continues past termination (held terminal state)
)
METHODS = (METHOD, TRACK)
