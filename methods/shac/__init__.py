"""shac: Short-Horizon Actor-Critic on the TRUE reward (a reference, ILD paper A.3)."""
from bench.api import MethodSpec, Uses
from methods.shac.config import PRESETS, TASK_OVERRIDES, SHACConfig
from methods.shac.train import train

METHOD = MethodSpec(
    name="shac",
    train=train,
    config_cls=SHACConfig,
    uses=Uses(true_reward=True, sim_gradients=True),
    description="reference: RL on the true reward through the differentiable simulator "
                "(32-step windows, TD-lambda critic); not an imitation method",
    presets=PRESETS,
    task_overrides=TASK_OVERRIDES,
    reference=True,
    version="2",  # bumped when its results change (CHANGELOG.md says why)
)
