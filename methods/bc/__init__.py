"""bc: behaviour cloning from the demo (the paper's BC warm start as a method of its own)."""
from bench.api import MethodSpec, Uses
from methods.bc.config import PRESETS, BCConfig
from methods.bc.train import train

METHOD = MethodSpec(
    name="bc",
    train=train,
    config_cls=BCConfig,
    uses=Uses(demo_states=True, demo_actions=True),
    description="behaviour cloning: tanh-Gaussian MLP fit to the demo's (o_t, a_t) pairs",
    presets=PRESETS,
    version="2",  # 2: the observation normalizer is frozen (it had gradients)
)
