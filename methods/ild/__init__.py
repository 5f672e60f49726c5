"""ild: Imitation Learning via Differentiable Physics (the paper's method)."""
from bench.api import MethodSpec, Uses
from methods.ild.config import PRESETS, TASK_OVERRIDES, ILDConfig
from methods.ild.train import train

METHOD = MethodSpec(
    name="ild",
    train=train,
    config_cls=ILDConfig,
    # Demo actions only feed the BC warm start (Alg. 1 line 3).
    uses=Uses(demo_states=True, demo_actions=True, sim_gradients=True),
    description="Chamfer-alpha to the demo states, backpropagated through the physics "
                "(truncated BPTT, per-step gradient normalization, BC warm start)",
    presets=PRESETS,
    task_overrides=TASK_OVERRIDES,
    version="5",  # bumped when its results change (CHANGELOG.md says why)
)
