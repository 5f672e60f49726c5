"""dac: Discriminator-Actor-Critic (Kostrikov et al. 2019) with SB3's TD3, one demo."""
from bench.api import MethodSpec, Uses
from methods.dac.config import PRESETS, DACConfig
from methods.dac.train import train

METHOD = MethodSpec(
    name="dac",
    train=train,
    config_cls=DACConfig,
    uses=Uses(demo_states=True, demo_actions=True),
    description="TD3 on a discriminator reward (logit of D(s, a)) with gradient penalty and "
                "absorbing states",
    presets=PRESETS,
    version="2",
    min_env_steps=1_000_000,  # the original trained for 1M env steps
)
