"""ild: Imitation Learning via Differentiable Physics (the paper's method)."""
from bench.api import MethodSpec, Uses
from methods.ild.config import (HAND_ADJOINT_PIECES, PLATFORM_OVERRIDES, PRESETS, TASK_OVERRIDES,
                               ILDConfig)
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
    platform_overrides=PLATFORM_OVERRIDES,  # ant's and humanoid's on a GPU
    # the spring substep's scene-specific pieces need its hand-written VJPs: turning
    # hand_adjoint off (--set hand_adjoint=false) takes their task overrides with it; so does
    # turning planar_adjoint off take planar_links (its form over all links) and
    # planar_normal_gravity (how it models reacher's gravity)
    requires={**{f: "hand_adjoint" for f in HAND_ADJOINT_PIECES},
              "planar_links": "planar_adjoint", "planar_normal_gravity": "planar_adjoint"},
    version="5",  # 3: mask_after_done option; 4: observation normalizer frozen;
    # 5: substep_remat on by default (ant's remat override dropped)
)
