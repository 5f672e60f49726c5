"""pwil: Primal Wasserstein Imitation Learning (Dadashi et al. 2021) with SB3's TD3."""
from bench.api import MethodSpec, Uses
from methods.pwil.config import PRESETS, TASK_OVERRIDES, PWILConfig
from methods.pwil.train import train

METHOD = MethodSpec(
    name="pwil",
    train=train,
    config_cls=PWILConfig,
    uses=Uses(demo_states=True, demo_actions=True),
    description="TD3 on a greedy Wasserstein-coupling reward to the demo's (s, a) atoms",
    presets=PRESETS,
    version="2",
    min_env_steps=1_000_000,  # the original trained for 1M env steps
    task_overrides=TASK_OVERRIDES,
)
