"""results/substep/scripts/free_piece_bound.py (session 49) times ILD's update with one piece
of the spring substep's backward made free. Its stand-in for a brax module must be that
module with one function's backward cut, and nothing else missing: before session 57 the
stand-in held only that function, so `tasks.spring_adjoint`'s hinge and planar-root forces
(sessions 51-53), which call `kinematics.link_to_joint_frame`, failed to trace under the
`inverse` and `all` pieces."""

import jax
import jax.numpy as jnp
import pytest
from brax import contact, kinematics, scan


@pytest.fixture(scope="module")
def fpb(substep_script):
    with substep_script("free_piece_bound") as mod:
        yield mod


def test_a_stand_in_is_its_module_with_one_backward_cut(fpb):
    patches = fpb._module_patches("all")
    assert patches["kinematics"].link_to_joint_frame is kinematics.link_to_joint_frame
    assert patches["kinematics"].inverse is not kinematics.inverse
    assert patches["scan"].tree is scan.tree and patches["contact"].get is not contact.get
    assert set(fpb._module_patches("inverse")) == {"kinematics"}
    # The cut function computes the same value with a zero gradient.
    f = fpb._free(lambda x: jnp.sin(x) * 2.0)
    assert float(f(1.0)) == pytest.approx(2 * float(jnp.sin(1.0)))
    assert float(jax.grad(f)(1.0)) == 0.0


def test_free_backward_puts_every_patch_back(fpb):
    import brax.kinematics

    import tasks.spring_adjoint as sa
    before = {name: getattr(sa, name) for name in ("kinematics", "scan", "contact", "actuator",
                                                   "_impulse")}
    axis_angle = brax.kinematics.axis_angle_ang
    with fpb.free_backward("all"):
        assert sa.kinematics.axis_angle_ang is brax.kinematics.axis_angle_ang
        assert brax.kinematics.axis_angle_ang is not axis_angle  # the stand-in sees the cut
    assert {name: getattr(sa, name) for name in before} == before
    assert brax.kinematics.axis_angle_ang is axis_angle
