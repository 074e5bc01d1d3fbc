"""`step`'s pose pass after resets (`MjxPixelEnv._poses`): with cameras and lights fixed in the
world (the Incline and Reacher Rearrange scenes) it is the kinematics pass, not MJX's full forward pass,
and gives the same episodes bit for bit: states, rewards, ends and frames equal to those of the
forward pass over steps in which worlds end and are reset, from the reset pool and (pool off)
from chunked resets, which start from the template Data whose camera poses `view_poses` set."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import bulbjax
from bulbjax.envs.env_config import pose_select

N, STEPS = 4, 24  # GeomOnIncline episodes last ~16 steps under random pushes: every world resets


def _rollout(env) -> dict[str, np.ndarray]:
    @jax.jit
    def run(key):
        state = env.reset(key)

        def body(st, k):
            a = jax.random.uniform(k, (N, env.action_size), minval=-1.0, maxval=1.0)
            st = env.step(st, a)
            return st, {"qpos": st.data.qpos, "qvel": st.data.qvel, "obs": st.obs, "reward": st.reward,
                        "done": st.done, "pixels": st.pixels, "geom_xpos": st.data.geom_xpos}
        return jax.lax.scan(body, state, jax.random.split(jax.random.PRNGKey(7), STEPS))[1]
    return jax.tree.map(np.asarray, run(jax.random.PRNGKey(3)))


# the chunked path (pool off, or `reset_with`'s fixed draws) in the slow tier: ~110 s of compile
@pytest.mark.parametrize("pool", [None, pytest.param(0, marks=pytest.mark.slow)], ids=["pool", "chunks"])
def test_kinematics_after_resets_gives_the_forward_passes_episodes(pool):
    lean = bulbjax.make("GeomOnIncline", num_envs=N, resolution=16, reset_pool=pool)
    full = bulbjax.make("GeomOnIncline", num_envs=N, resolution=16, reset_pool=pool)
    assert lean._pose_pass == "kinematics", "the Incline's camera and light are fixed in the world"
    full._pose_pass = "forward"  # the full forward pass after resets, as before the kinematics pass
    a, b = _rollout(lean), _rollout(full)
    assert a["done"].sum() >= N, f"every world should end at least once in {STEPS} steps: {a['done'].sum()} ends"
    assert a["pixels"].std() > 0, "the frames show a scene"
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_a_moving_camera_or_an_action_that_reads_dynamics_keeps_the_forward_pass():
    assert bulbjax.make("CartPole", num_envs=2, render=False)._pose_pass == "forward", \
        "CartPole's camera rides on the cart: only the forward pass places it"
    assert bulbjax.make("FrankaRearrangeGeom", num_envs=2, render=False)._pose_pass == "forward", \
        "the Franka's gravity compensation reads qfrc_bias, which only the forward pass computes"
    assert bulbjax.make("ReacherRearrangeGeom", num_envs=2, render=False)._pose_pass == "kinematics"


def test_graph_mode_is_checked_and_has_no_effect_on_the_cpu():
    from bulbjax.envs import warp_graphs

    with pytest.raises(ValueError, match="graph_mode must be"):
        bulbjax.make("CartPole", num_envs=2, render=False, graph_mode="fast")
    env = bulbjax.make("CartPole", num_envs=2, render=False, graph_mode="jax")
    assert env.config.graph_mode == "jax"
    assert warp_graphs.graph_mode("jax", jax.devices("cpu")[0]) is None, "the CPU never captures graphs"

    class Gpu:
        platform = "gpu"
    assert int(warp_graphs.graph_mode("warp_staged", Gpu())) == 3, "Warp's JaxCallableGraphMode.WARP_STAGED"


def test_the_pose_pass_as_a_select_gives_the_cond_s_episodes_with_one_branch_fewer():
    """`EnvConfig.reset_pose_branch`: "select" runs the pose pass in every step and keeps it where
    some world was reset, so a GPU never reads that predicate on the host; the episodes are the
    cond's bit for bit (poses included) and the step holds one `lax.cond` fewer."""
    make = lambda branch: bulbjax.make("InvertedPendulum", num_envs=N, render=False,  # noqa: E731
                                       reset_pose_branch=branch)
    cond, select = make("cond"), make("select")
    assert select._pose_select and not cond._pose_select
    assert not bulbjax.make("InvertedPendulum", num_envs=2, render=False)._pose_select, "auto on a CPU: the cond"
    a, b = _rollout(select), _rollout(cond)
    assert 0 < a["done"].sum() < a["done"].size, "some steps must reset a world and some not"
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    state, act = cond.reset(jax.random.PRNGKey(0)), np.zeros((N, cond.action_size), np.float32)
    branches = lambda env: jax.jit(env.step).lower(state, act).as_text().count("stablehlo.case")  # noqa: E731
    assert branches(cond) == branches(select) + 1
    with pytest.raises(ValueError, match="reset_pose_branch must be one of"):
        make("where")


def test_auto_picks_the_select_on_a_gpu_where_the_pose_pass_is_the_kinematics_pass():
    """`EnvConfig.reset_pose_branch` "auto": the select where it measured faster (a GPU, the
    kinematics pass: Fig. 5), the cond where the pass is MJX's forward pass (HalfCheetah: the
    select measured slower) and on a CPU (no predicate read on a host)."""
    assert pose_select("auto", "kinematics", "gpu")
    assert not pose_select("auto", "forward", "gpu")
    assert not pose_select("auto", "kinematics", "cpu")
    assert pose_select("select", "forward", "cpu") and not pose_select("cond", "kinematics", "gpu")
    assert bulbjax.make("GeomOnIncline", num_envs=1, render=False)._pose_pass == "kinematics"
    assert bulbjax.make("InvertedPendulum", num_envs=1, render=False)._pose_pass == "forward"
