"""Environments: CartPole, CartPoleContinuous, InvertedPendulum (and the multicolour variant).

Shapes/dtypes, determinism, reset distributions, physics against MuJoCo C and the analytic
one-step value, termination / truncation / auto-reset bookkeeping, frames (camera, known pixel
colours, multicolour schemes) and bad actions. Every env is built and jit-compiled once per
module (small batches, `env_bundles.py`) so the file stays fast on a 2-core CPU; the state specs
and the registry's errors, which build no model, are in test_env_registry.py.

Note: results of a jitted reset/step/render are dispatched asynchronously; if the env (and so its
Warp render context) is dropped while one is still in flight, that computation fails with
`KeyError: (context_id, -1)` in refit_bvh. Tests block on results they do not otherwise read.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from bulbjax.envs import EnvState, RenderInput
from bulbjax.envs.colours import SCHEMES

from env_bundles import (RES, Bundle, N, _action, _bundle, _check_fields, _is_blue, _matches_colour,
                         _mujoco_reference, _push_right, _rgb, _rollout, _set_state)

N_MC = 8  # worlds of the multicolour env (several schemes drawn)
CP_THETA_MAX = 12 * 2 * math.pi / 360
WHITE = np.array([255, 255, 255], np.uint8)


@pytest.fixture(scope="module")
def cartpole() -> Bundle:
    return _bundle("CartPole")


@pytest.fixture(scope="module")
def cartpole_cont() -> Bundle:
    return _bundle("CartPoleContinuous")


@pytest.fixture(scope="module")
def inv_pend() -> Bundle:
    return _bundle("InvertedPendulum")


@pytest.fixture(scope="module")
def cartpole_norender() -> Bundle:
    return _bundle("CartPole", render=False)


@pytest.fixture(scope="module")
def multicolour() -> Bundle:
    return _bundle("CartPoleMulticolour", num_envs=N_MC)


ENV_FIXTURES = ["cartpole", "cartpole_cont", "inv_pend"]


# --------------------------------------------------------------------------------------------
# shapes, dtypes, attributes
# --------------------------------------------------------------------------------------------

EXPECTED_ATTRS = {
    "CartPole": dict(state_dim=4, discrete=True, num_actions=2, episode_length=200, timestep=0.02),
    "CartPoleContinuous": dict(state_dim=4, discrete=False, num_actions=None, episode_length=200, timestep=0.02),
    "InvertedPendulum": dict(state_dim=5, discrete=False, num_actions=None, episode_length=1000, timestep=0.0165),
}


@pytest.mark.parametrize("fixture", ENV_FIXTURES)
def test_shapes_and_dtypes_after_reset_and_step(fixture: str, request: pytest.FixtureRequest) -> None:
    b: Bundle = request.getfixturevalue(fixture)
    env = b.env
    exp = EXPECTED_ATTRS[env.name]
    assert env.state_dim == env.obs_size == exp["state_dim"] == len(env.state_spec)
    assert env.discrete is exp["discrete"] and env.num_actions == exp["num_actions"]
    assert env.action_size == 1 and env.episode_length == exp["episode_length"]
    assert env.frame_shape == (RES, RES, 3) and env.num_envs == N
    assert env.mj_model.opt.timestep == pytest.approx(exp["timestep"])
    assert env.mj_model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER  # semi-implicit, as PyBullet

    s0 = b.reset(jax.random.PRNGKey(0))
    _check_fields(env, s0, RES)
    np.testing.assert_array_equal(s0.reward, 0.0)
    np.testing.assert_array_equal(s0.done, 0.0)
    np.testing.assert_array_equal(s0.step_count, 0)
    s1 = b.step(s0, _action(env, 1))
    _check_fields(env, s1, RES)
    np.testing.assert_array_equal(s1.reward, 1.0)  # +1 per step in all three domains
    np.testing.assert_array_equal(s1.done, 0.0)
    np.testing.assert_array_equal(s1.step_count, 1)
    np.testing.assert_array_equal(s1.episode_return, 1.0)


def test_render_false_gives_empty_pixels(cartpole_norender: Bundle) -> None:
    b = cartpole_norender
    s0 = b.reset(jax.random.PRNGKey(0))
    s1 = b.step(s0, _action(b.env, 0))
    for s in (s0, s1):
        assert s.pixels.shape == (N, 0, 0, 3) and s.pixels.dtype == jnp.uint8
        assert s.lowdim.shape == (N, 4) and s.lowdim.dtype == jnp.float32
    with pytest.raises(ValueError, match="render=True"):
        b.env.render_frames(s1.render_input)


# --------------------------------------------------------------------------------------------
# determinism and reset distributions
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fixture", ENV_FIXTURES)
def test_same_key_same_rollout_different_key_different_state(fixture: str, request: pytest.FixtureRequest) -> None:
    b: Bundle = request.getfixturevalue(fixture)
    actions = [_action(b.env, a) for a in (1, 0, 1)]
    r1 = _rollout(b, jax.random.PRNGKey(7), actions)
    r2 = _rollout(b, jax.random.PRNGKey(7), actions)
    for s1, s2 in zip(r1, r2):
        np.testing.assert_array_equal(s1.lowdim, s2.lowdim)
        np.testing.assert_array_equal(s1.pixels, s2.pixels)
    # frames follow the state: consecutive frames of a moving system differ
    assert not np.array_equal(r1[0].pixels, r1[-1].pixels)
    other = b.reset(jax.random.PRNGKey(8))
    assert not np.allclose(other.lowdim, r1[0].lowdim)
    # worlds of one batch start from different states
    lowdim = np.asarray(r1[0].lowdim)
    assert len({tuple(row) for row in lowdim}) == N


@pytest.mark.parametrize("fixture", ["cartpole", "cartpole_cont"])
def test_cartpole_reset_noise_within_pybullet_bounds(fixture: str, request: pytest.FixtureRequest) -> None:
    b: Bundle = request.getfixturevalue(fixture)
    lowdim = np.concatenate([np.asarray(b.reset(jax.random.PRNGKey(k)).lowdim) for k in range(4)])
    assert np.all(np.abs(lowdim) <= 0.05 + 1e-7), lowdim
    # uniform on all four entries: not stuck at zero, spread over the interval
    assert np.all(lowdim.std(0) > 0.01), lowdim.std(0)
    s = b.reset(jax.random.PRNGKey(0))
    # lowdim order theta, theta_vel, x, x_vel; qpos = (x, theta), qvel = (x_vel, theta_vel)
    np.testing.assert_allclose(s.lowdim[:, [2, 0]], s.data.qpos, atol=1e-7)
    np.testing.assert_allclose(s.lowdim[:, [3, 1]], s.data.qvel, atol=1e-7)


def test_inverted_pendulum_reset_noise_within_pybullet_bounds(inv_pend: Bundle) -> None:
    lowdim = np.concatenate([np.asarray(inv_pend.reset(jax.random.PRNGKey(k)).lowdim) for k in range(4)])
    x, x_vel, c, s, theta_vel = lowdim.T
    np.testing.assert_array_equal(x, 0.0)
    np.testing.assert_array_equal(x_vel, 0.0)
    np.testing.assert_array_equal(theta_vel, 0.0)
    np.testing.assert_allclose(c ** 2 + s ** 2, 1.0, atol=1e-6)
    theta = np.arctan2(s, c)
    assert np.all(np.abs(theta) <= 0.1 + 1e-6), theta
    assert theta.std() > 0.02 and np.any(theta > 0) and np.any(theta < 0)


# --------------------------------------------------------------------------------------------
# physics
# --------------------------------------------------------------------------------------------

def test_cartpole_one_step_from_rest_matches_analytic_semi_implicit_euler(cartpole_norender: Bundle) -> None:
    """From rest at theta=0, one 10 N step: v1 = dt * M^-1 [F, 0], q1 = dt * v1 (semi-implicit Euler).

    M is the cart-pole mass matrix of the model PyBullet simulates (cart 1 kg; pole 0.1 kg with its
    COM at l = 0.5 m and the inertia Bullet computes from the 0.05x0.05x1 m box, m (w^2 + h^2) / 12
    = 0.00835 kg m^2 about the hinge axis through the COM): [[m_c + m_p, m_p l cos], [m_p l cos, I + m_p l^2]].
    The off-diagonal term does not vanish at theta=0, so x_vel is dt * F * M22 / det(M), slightly
    above dt * F / (m_c + m_p)."""
    b = cartpole_norender
    dt, force = 0.02, 10.0
    assert b.env.mj_model.opt.timestep == dt
    m_c, m_p, l = 1.0, 0.1, 0.5
    inertia = m_p * (0.05 ** 2 + 1.0 ** 2) / 12
    mass = np.array([[m_c + m_p, m_p * l], [m_p * l, inertia + m_p * l ** 2]])
    # the compiled model has that mass matrix (MuJoCo C on the CPU)
    d = mujoco.MjData(b.env.mj_model)
    mujoco.mj_forward(b.env.mj_model, d)
    full = np.zeros((2, 2))
    mujoco.mj_fullM(b.env.mj_model, d, full)
    np.testing.assert_allclose(full, mass, atol=1e-9)
    qacc = np.linalg.solve(mass, [force, 0.0])  # no gravity torque or bias at theta=0, rest
    v1 = dt * qacc
    q1 = dt * v1

    s = _set_state(b.reset(jax.random.PRNGKey(0)), np.zeros((N, 2)), np.zeros((N, 2)))
    s1 = jax.device_get(b.step(s, _action(b.env, 1)))
    theta, theta_vel, x, x_vel = np.asarray(s1.lowdim).T
    np.testing.assert_allclose(x_vel, v1[0], atol=1e-5)
    np.testing.assert_allclose(theta_vel, v1[1], atol=1e-5)
    np.testing.assert_allclose(x, q1[0], atol=1e-6)
    np.testing.assert_allclose(theta, q1[1], atol=1e-6)
    assert x_vel[0] > 0 and theta_vel[0] < 0  # cart goes +x, pole lags behind (tilts to -theta)
    # the decoupled estimate F / (m_c + m_p) is off by the pole coupling (~4e-4 m/s here)
    assert abs(x_vel[0] - dt * force / (m_c + m_p)) > 2e-4


@pytest.fixture(scope="module")
def cp_push_right(cartpole: Bundle) -> list[EnvState]:
    """CartPole pushed right (+10 N) for 24 steps from reset(PRNGKey(3)): every world ends once."""
    return _rollout(cartpole, jax.random.PRNGKey(3), [_push_right(cartpole.env)] * 24)


def _first_done(states: list[EnvState]) -> np.ndarray:
    done = np.stack([np.asarray(s.done) for s in states[1:]])  # [T, N]
    assert np.all(done.any(0)), "every world should have ended"
    return done.argmax(0) + 1  # step index (1-based) of the first terminal step per world


def test_cartpole_push_right_terminates_like_pybullet(cartpole: Bundle, cp_push_right: list[EnvState]) -> None:
    states, env = cp_push_right, cartpole.env
    t_end = _first_done(states)
    # The pole (Bullet's box inertia, 0.00835 kg m^2) tips past 12 degrees after ~8 pushes, before
    # the cart reaches 0.4 m (checked against MuJoCo C below)
    assert np.all((t_end >= 5) & (t_end <= 12)), t_end
    for w in range(N):
        traj = np.stack([np.asarray(states[t].lowdim[w]) for t in range(t_end[w])])  # before the end
        theta, _, x, x_vel = traj.T
        assert np.all(np.diff(x_vel) > 0.15), x_vel  # accelerates in +x every step
        assert x[-1] > x[0] + 0.05
        assert np.all(np.abs(x) <= 0.4) and np.all(np.abs(theta) <= CP_THETA_MAX)
        # MuJoCo C from the same start: same trajectory, and the episode ends exactly when the
        # state leaves |x| <= 0.4, |theta| <= 12 deg (here by theta: the pole lags the pushed cart)
        s0 = states[0]
        qs, vs = _mujoco_reference(env.mj_model, np.asarray(s0.data.qpos[w], np.float64),
                                   np.asarray(s0.data.qvel[w], np.float64), np.array([10.0]), 24)
        ref = np.stack([qs[:, 1], vs[:, 1], qs[:, 0], vs[:, 0]], 1)  # theta, theta_vel, x, x_vel
        np.testing.assert_allclose(traj[1:], ref[: t_end[w] - 1], atol=2e-4)
        out = (np.abs(ref[:, 2]) > 0.4) | (np.abs(ref[:, 0]) > CP_THETA_MAX)
        assert out.argmax() + 1 == t_end[w]
        assert abs(ref[t_end[w] - 1, 0]) > CP_THETA_MAX and abs(ref[t_end[w] - 1, 2]) < 0.4


def test_cartpole_auto_reset_after_termination(cartpole: Bundle, cp_push_right: list[EnvState]) -> None:
    states = cp_push_right
    t_end = _first_done(states)
    for t in range(1, len(states)):
        s, prev = states[t], states[t - 1]
        done = np.asarray(s.done) > 0
        np.testing.assert_array_equal(s.reward, 1.0)  # PyBullet pays 1 on the terminal step too
        np.testing.assert_array_equal(s.truncated, 0.0)  # terminated, not truncated
        np.testing.assert_array_equal(np.asarray(s.step_count)[done], 0)
        np.testing.assert_array_equal(np.asarray(s.step_count)[~done], np.asarray(prev.step_count)[~done] + 1)
        np.testing.assert_array_equal(np.asarray(s.info["episode_length"])[done],
                                      np.asarray(prev.step_count)[done] + 1)
        np.testing.assert_allclose(np.asarray(s.info["episode_return"])[done],
                                   np.asarray(prev.episode_return)[done] + 1)
        np.testing.assert_array_equal(np.asarray(s.info["episode_length"])[~done], 0)
        np.testing.assert_array_equal(np.asarray(s.episode_return)[done], 0.0)
        # the worlds just reset start a new episode inside the reset bounds
        assert np.all(np.abs(np.asarray(s.lowdim)[done]) <= 0.05 + 1e-7)
    for w in range(N):
        s = states[t_end[w]]
        assert s.info["episode_length"][w] == t_end[w]
        assert s.info["episode_return"][w] == pytest.approx(float(t_end[w]))
    # obs and frame of a terminal step are those of the new episode's first state
    s = states[int(t_end.min())]
    np.testing.assert_array_equal(s.pixels, np.asarray(cartpole.render(s.render_input)))


def test_cartpole_truncates_at_200_steps(cartpole_norender: Bundle) -> None:
    """Upright at rest, a bang-bang feedback push (right when theta + 0.2 theta_vel + 0.1 x +
    0.2 x_vel > 0) keeps the pole up for 200 steps: the 200th step ends the episode by the time
    limit (truncated=1, done=1, episode_length=200, return=200)."""
    b = cartpole_norender
    s = _set_state(b.reset(jax.random.PRNGKey(0)), np.zeros((N, 2)), np.zeros((N, 2)))
    left = _action(b.env, 0)

    def push(lowdim: jax.Array) -> jax.Array:
        theta, theta_vel, x, x_vel = np.asarray(lowdim).T
        return jnp.asarray(theta + 0.2 * theta_vel + 0.1 * x + 0.2 * x_vel > 0, jnp.int32)

    max_theta = max_x = 0.0
    for t in range(1, 200):
        s = b.step(s, push(s.lowdim))
        assert not np.any(np.asarray(s.done)), f"ended early at step {t}"
        max_theta = max(max_theta, float(np.abs(s.lowdim[:, 0]).max()))
        max_x = max(max_x, float(np.abs(s.lowdim[:, 2]).max()))
    np.testing.assert_array_equal(s.step_count, 199)
    s = jax.device_get(b.step(s, left))
    np.testing.assert_array_equal(s.done, 1.0)
    np.testing.assert_array_equal(s.truncated, 1.0)
    np.testing.assert_array_equal(s.info["episode_length"], 200)
    np.testing.assert_allclose(s.info["episode_return"], 200.0)
    np.testing.assert_array_equal(s.step_count, 0)
    assert np.all(np.abs(s.lowdim) <= 0.05 + 1e-7)  # auto-reset
    assert max_theta < CP_THETA_MAX and max_x < 0.4


def test_cartpole_continuous_scales_and_clips_force(cartpole: Bundle, cartpole_cont: Bundle) -> None:
    """Continuous force = clip(a, -1, 1) * 10 N: a=+1 (and a=3) match the discrete push right, and
    the force's share of the velocity change (beyond the zero-force change) is linear in a."""
    key = jax.random.PRNGKey(11)
    zero = _rollout(cartpole_cont, key, [_action(cartpole_cont.env, 0.0)] * 3)
    disc = _rollout(cartpole, key, [_action(cartpole.env, 1)] * 3)
    cont = _rollout(cartpole_cont, key, [_action(cartpole_cont.env, 1.0)] * 3)
    clipped = _rollout(cartpole_cont, key, [_action(cartpole_cont.env, 3.0)] * 3)
    half = _rollout(cartpole_cont, key, [_action(cartpole_cont.env, 0.5)] * 3)
    np.testing.assert_array_equal(disc[0].lowdim, cont[0].lowdim)  # same reset distribution
    for d, c, k in zip(disc, cont, clipped):
        np.testing.assert_allclose(c.lowdim, d.lowdim, atol=1e-6)
        np.testing.assert_allclose(k.lowdim, d.lowdim, atol=1e-6)
    dv_full = np.asarray(cont[1].lowdim[:, 3] - cont[0].lowdim[:, 3])
    dv_half = np.asarray(half[1].lowdim[:, 3] - half[0].lowdim[:, 3])
    dv_zero = np.asarray(zero[1].lowdim[:, 3] - zero[0].lowdim[:, 3])
    np.testing.assert_allclose(dv_half - dv_zero, (dv_full - dv_zero) / 2, atol=1e-5)
    assert np.all(dv_full > 0.15)


def test_inverted_pendulum_push_right_matches_mujoco_and_terminates(inv_pend: Bundle) -> None:
    """Torque 100 * a on the slider (dt 0.0165): cart accelerates +x, the pole falls back and the
    episode ends on the step where |theta| > 0.2; the next state is a fresh reset."""
    b = inv_pend
    assert b.env.mj_model.opt.timestep == pytest.approx(0.0165)
    states = _rollout(b, jax.random.PRNGKey(5), [_push_right(b.env)] * 20)
    t_end = _first_done(states)
    for w in range(N):
        qs, vs = _mujoco_reference(b.env.mj_model, np.asarray(states[0].data.qpos[w], np.float64),
                                   np.asarray(states[0].data.qvel[w], np.float64), np.array([1.0]), 20)
        ref = np.stack([qs[:, 0], vs[:, 0], np.cos(qs[:, 1]), np.sin(qs[:, 1]), vs[:, 1]], 1)
        traj = np.stack([np.asarray(states[t].lowdim[w]) for t in range(1, t_end[w])])
        np.testing.assert_allclose(traj, ref[: t_end[w] - 1], atol=2e-3, rtol=1e-3)
        assert np.all(np.diff(traj[:, 1]) > 0)  # x_vel grows
        assert (np.abs(qs[:, 1]) > 0.2).argmax() + 1 == t_end[w]
        s = states[t_end[w]]
        assert s.step_count[w] == 0 and s.info["episode_length"][w] == t_end[w]
        x, x_vel, c, sn, theta_vel = np.asarray(s.lowdim[w])
        assert x == 0 and x_vel == 0 and theta_vel == 0 and abs(math.atan2(sn, c)) <= 0.1 + 1e-6
        assert s.truncated[w] == 0


# --------------------------------------------------------------------------------------------
# frames
# --------------------------------------------------------------------------------------------

def _upright(n: int, x: float = 0.0, theta: float = 0.0) -> jax.Array:
    return jnp.tile(jnp.array([[x, theta]], jnp.float32), (n, 1))


def test_frame_changes_only_around_the_pole(cartpole: Bundle) -> None:
    scheme = jnp.zeros(N, jnp.int32)
    f0 = np.asarray(cartpole.render(RenderInput(qpos=_upright(N), scheme=scheme)))
    f1 = np.asarray(cartpole.render(RenderInput(qpos=_upright(N, theta=0.4), scheme=scheme)))
    diff = np.any(f0 != f1, -1)  # [N, H, W]
    assert diff.sum() > 20
    rows, cols = np.nonzero(diff[0])
    assert rows.max() < RES // 2 - 1  # only above the cart, where the pole is
    assert cols.min() >= RES // 2 - 3  # the pole tilts to +x, i.e. to the right of the image
    np.testing.assert_array_equal(f0[:, RES // 2 :], f1[:, RES // 2 :])  # cart and rail untouched
    # the same qpos renders the same frame in every world
    for w in range(1, N):
        np.testing.assert_array_equal(f0[w], f0[0])


def test_reset_frames_show_the_reset_state(cartpole: Bundle, inv_pend: Bundle) -> None:
    for b in (cartpole, inv_pend):
        s = b.reset(jax.random.PRNGKey(1))
        np.testing.assert_array_equal(s.pixels, np.asarray(b.render(s.render_input)))


def test_step_frames_show_the_new_state(cartpole: Bundle, cp_push_right: list[EnvState]) -> None:
    """The frame reported with a step shows the same state as its lowdim (PyBullet renders after
    stepSimulation): state.pixels == render_frames(state.render_input) at every step."""
    for t, s in enumerate(cp_push_right[1:6], start=1):
        assert not np.any(s.done)
        np.testing.assert_array_equal(s.pixels, np.asarray(cartpole.render(s.render_input)),
                                      err_msg=f"step {t}")


def test_known_pixels_cart_pole_background(cartpole: Bundle) -> None:
    c = RES // 2
    scheme = jnp.zeros(N, jnp.int32)
    for x in (0.0, 0.3):  # the camera targets the cart, so the cart stays at the centre
        f = np.asarray(cartpole.render(RenderInput(qpos=_upright(N, x=x), scheme=scheme)))[0]
        assert _matches_colour(f[c, c], np.array([1, 1, 0])), f[c, c]  # yellow cart
        # upright pole above the centre (1-2 px wide at 64x64): blue-dominant
        for row in (c - 8, c - 16, c - 24):
            assert any(_is_blue(f[row, col]) for col in range(c - 2, c + 2)), f[row, c - 2 : c + 2]
        for corner in (f[0, 0], f[0, -1], f[-1, 0], f[-1, -1]):
            np.testing.assert_array_equal(corner, WHITE)  # background
    # reset frames too: the cart is at the centre whatever the sampled x
    s = cartpole.reset(jax.random.PRNGKey(0))
    for w in range(N):
        assert _matches_colour(np.asarray(s.pixels[w, c, c]), np.array([1, 1, 0]))


def test_inverted_pendulum_frame(inv_pend: Bundle) -> None:
    s = inv_pend.reset(jax.random.PRNGKey(0))
    f = np.asarray(s.pixels)
    c = RES // 2
    for w in range(N):
        r, g, bl = _rgb(f[w, c, c])
        assert r > 150 and g > 150 and bl < 110  # olive/yellow cart (rgba 0.7 0.7 0) at the centre
        np.testing.assert_array_equal(f[w, 0, 0], WHITE)
        np.testing.assert_array_equal(f[w, -1, -1], WHITE)
    assert not np.array_equal(f[0], f[2])  # different pole angles


# --------------------------------------------------------------------------------------------
# multicolour
# --------------------------------------------------------------------------------------------

def test_multicolour_schemes_colour_cart_and_pole(multicolour: Bundle, cartpole: Bundle) -> None:
    b = multicolour
    assert b.env.config.multicolour
    c = RES // 2
    s = b.reset(jax.random.PRNGKey(0))
    schemes = np.asarray(s.scheme)
    assert np.all((schemes >= 0) & (schemes < 4))
    assert len(set(schemes.tolist())) >= 2, schemes
    f = np.asarray(s.pixels)
    for w in range(N_MC):
        base = SCHEMES["base"][schemes[w]]
        assert _matches_colour(f[w, c, c], base), (schemes[w], f[w, c, c])
    for v in range(N_MC):
        for w in range(N_MC):
            if schemes[v] != schemes[w]:
                assert not np.array_equal(f[v, c, c], f[w, c, c])
    # over a few resets every scheme is drawn
    drawn = set(schemes.tolist())
    for k in range(1, 4):
        drawn |= set(np.asarray(b.reset(jax.random.PRNGKey(k)).scheme).tolist())
    assert drawn == {0, 1, 2, 3}
    # the plain env never changes colours
    np.testing.assert_array_equal(cartpole.reset(jax.random.PRNGKey(0)).scheme, 0)

    # all four schemes, upright: cart base colour at the centre, pole colour above it
    sch = jnp.arange(N_MC, dtype=jnp.int32) % 4
    frames = np.asarray(b.render(RenderInput(qpos=_upright(N_MC), scheme=sch)))
    for w in range(4):
        assert _matches_colour(frames[w, c, c], SCHEMES["base"][w]), (w, frames[w, c, c])
        pole = SCHEMES["pole"][w]
        assert any(_matches_colour(frames[w, c - 16, col], pole) for col in range(c - 2, c + 2)), \
            (w, frames[w, c - 16, c - 2 : c + 2])
        np.testing.assert_array_equal(frames[w, 0, 0], WHITE)
    # scheme 0 is the plain colouring
    plain = np.asarray(cartpole.render(RenderInput(qpos=_upright(N), scheme=jnp.zeros(N, jnp.int32))))
    np.testing.assert_array_equal(frames[0], plain[0])


def test_multicolour_scheme_fixed_within_episode(multicolour: Bundle) -> None:
    b = multicolour
    s = b.reset(jax.random.PRNGKey(0))
    a = _action(b.env, 1)
    for _ in range(3):  # too few steps to end an episode
        s2 = b.step(s, a)
        assert not np.any(np.asarray(s2.done))
        np.testing.assert_array_equal(s2.scheme, s.scheme)
        s = s2


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("action, pattern", [
    (jnp.ones(N, jnp.float32), r"integer actions of shape \(4,\)"),  # float for a discrete env
    (jnp.ones((N, 1), jnp.int32), r"integer actions of shape \(4,\)"),  # [N, 1] instead of [N]
    (jnp.ones(N + 1, jnp.int32), r"integer actions of shape \(4,\)"),  # wrong batch
    (jnp.ones(N, jnp.bool_), r"integer actions"),  # bool is not an action index
])
def test_cartpole_bad_action_raises(cartpole: Bundle, action: jax.Array, pattern: str) -> None:
    # Wait for the reset: a Warp render still in flight when the env is dropped at module
    # teardown fails with KeyError (render context gone), see the module docstring.
    s = jax.block_until_ready(cartpole.reset(jax.random.PRNGKey(0)))
    with pytest.raises(ValueError, match=pattern) as e:
        cartpole.step(s, action)
    assert "[0, 2)" in str(e.value)


@pytest.mark.parametrize("action", [jnp.ones(N, jnp.float32), jnp.ones((N, 2), jnp.float32),
                                    jnp.ones((N + 1, 1), jnp.float32),
                                    jnp.ones((N, 1), jnp.int32)])  # integers are not silently cast
@pytest.mark.parametrize("fixture", ["cartpole_cont", "inv_pend"])
def test_continuous_bad_action_shape_raises(fixture: str, action: jax.Array, request: pytest.FixtureRequest) -> None:
    b: Bundle = request.getfixturevalue(fixture)
    s = jax.block_until_ready(b.reset(jax.random.PRNGKey(0)))
    with pytest.raises(ValueError, match=r"float actions of shape \(4, 1\) in \[-1, 1\]"):
        b.step(s, action)


def test_render_sequence_keeps_each_step_with_its_frames(cartpole: Bundle) -> None:
    """Several renders in one jitted call (what the experiment does) must each show their own
    stored step: frames of K tilted poles equal the one-at-a-time renders and differ between
    steps (on the H100, unordered renders in one jit once mixed frames up)."""
    s = jax.block_until_ready(cartpole.reset(jax.random.PRNGKey(3)))
    tilts = (0.3, -0.3, 0.0)
    ris = [RenderInput(qpos=s.render_input.qpos.at[:, 1].set(t), scheme=s.scheme) for t in tilts]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *ris)
    seq = np.asarray(jax.jit(cartpole.env.render_sequence)(stacked))
    assert seq.shape == (len(tilts), N, RES, RES, 3)
    for k, ri in enumerate(ris):
        np.testing.assert_array_equal(seq[k], np.asarray(cartpole.render(ri)), err_msg=f"step {k}")
    assert not np.array_equal(seq[0], seq[1]) and not np.array_equal(seq[1], seq[2])
