"""gymnasium and Brax adapters (bulbjax/interop/): check_env, autoreset against bulbjax's own
auto-reset, spaces, seeding, the Brax-style wrapper under jit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402

import bulbjax  # noqa: E402
from bulbjax.gym import BulbjaxVectorEnv, GymEnv, make_env, make_vec  # noqa: E402
from bulbjax.interop.brax import BraxEnv  # noqa: E402

N = 4
EP_LEN = 8  # CartPole pushed one way ends in 7-9 steps: short limit -> both terminations and truncations
ACTIONS = np.array([1, 0, 1, 0], np.int32)  # constant per world, so holding a world a step changes nothing


@pytest.fixture(scope="module")
def cartpole() -> bulbjax.envs.base.MjxPixelEnv:
    env = bulbjax.make("CartPole", num_envs=N, render=False)
    env.episode_length = EP_LEN  # instance override, read by step when first traced
    return env


@pytest.fixture(scope="module")
def vec_next(cartpole) -> BulbjaxVectorEnv:
    return BulbjaxVectorEnv(cartpole, obs="state", autoreset_mode="next_step")


def _reference(env, seed: int, steps: int):
    """Per-world episodes of bulbjax's own auto-reset: first obs, (length, return, truncated,
    last state before the reset) of each ended episode."""
    step = jax.jit(env.step)
    before_reset = jax.jit(lambda s, a: env._lowdim_batch(env.physics(s.data, a, s.params), s.params))
    s = jax.jit(env.reset)(jax.random.PRNGKey(seed))
    firsts = [[np.asarray(s.lowdim[i])] for i in range(N)]
    episodes = [[] for _ in range(N)]
    a = jnp.asarray(ACTIONS)
    for _ in range(steps):
        last = np.asarray(before_reset(s, a))
        s = step(s, a)
        done, trunc = np.asarray(s.done) > 0, np.asarray(s.truncated) > 0
        for i in np.flatnonzero(done):
            episodes[i].append((int(s.info["episode_length"][i]), float(s.info["episode_return"][i]),
                                bool(trunc[i]), last[i]))
            firsts[i].append(np.asarray(s.lowdim[i]))
    return firsts, episodes


def _run_gym(venv: BulbjaxVectorEnv, seed: int, steps: int):
    obs, _ = venv.reset(seed=seed)
    firsts = [[obs[i].copy()] for i in range(N)]
    episodes = [[] for _ in range(N)]
    running = np.zeros(N)
    length = np.zeros(N, int)
    pending = np.zeros(N, bool)  # next_step: the world's next obs is a reset obs
    next_step = venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    for _ in range(steps):
        obs, rew, term, trunc, info = venv.step(ACTIONS)
        assert obs.dtype == np.float32 and rew.dtype == np.float32 and term.dtype == np.bool_
        assert not (term & trunc).any()
        if next_step:
            for i in np.flatnonzero(pending):  # the reset step: new obs, no reward, no flags
                assert rew[i] == 0 and not term[i] and not trunc[i]
                firsts[i].append(obs[i].copy())
        live = ~pending if next_step else np.ones(N, bool)
        running += np.where(live, rew, 0)
        length += live
        done = term | trunc
        for i in np.flatnonzero(done):
            last = obs[i] if next_step else info["final_obs"][i]
            assert info["_episode_return"][i] and info["episode_return"][i] == running[i]
            assert info["episode_length"][i] == length[i]
            episodes[i].append((int(length[i]), float(running[i]), bool(trunc[i]), np.array(last)))
            if not next_step:
                firsts[i].append(obs[i].copy())
                assert info["_final_obs"][i] and info["final_info"]["_episode_return"][i]
        if not next_step:
            assert all(info["final_obs"][i] is None for i in np.flatnonzero(~done)) if done.any() else True
        running[done], length[done] = 0, 0
        pending = done if next_step else pending
    return firsts, episodes


@pytest.mark.parametrize("mode", ["next_step", "same_step"])
def test_vector_autoreset_matches_bulbjax(cartpole, vec_next, mode):
    venv = vec_next
    if mode == "same_step":
        venv = BulbjaxVectorEnv(cartpole, obs="state", autoreset_mode="same_step")
        venv.core = vec_next.core  # same compiled functions; only the host-side mapping differs
    ref_firsts, ref_eps = _reference(cartpole, seed=7, steps=30)
    firsts, eps = _run_gym(venv, seed=7, steps=30)
    kinds = set()
    for i in range(N):
        k = min(len(ref_eps[i]), len(eps[i]))
        assert k >= 2, "too few episodes to compare"
        for (rl, rr, rt, rlast), (gl, gr, gt, glast) in zip(ref_eps[i][:k], eps[i][:k]):
            assert (gl, gr, gt) == (rl, rr, rt)
            np.testing.assert_allclose(glast, rlast, atol=1e-6)  # the state before bulbjax's reset
            kinds.add(gt)
            if not gt:  # terminated: the last state is past CartPole's limits (12 degrees or 0.4 m)
                assert abs(glast[0]) > cartpole.theta_threshold or abs(glast[2]) > cartpole.x_threshold
        for rf, gf in zip(ref_firsts[i][:k + 1], firsts[i][:k + 1]):
            np.testing.assert_allclose(gf, rf, atol=1e-6)
    assert kinds == {True, False}, "expected both truncated and terminated episodes"
    assert venv.metadata["autoreset_mode"] == {"next_step": AutoresetMode.NEXT_STEP,
                                               "same_step": AutoresetMode.SAME_STEP}[mode]


def test_vector_spaces_seeding_and_errors(cartpole, vec_next):
    v = vec_next
    assert v.single_action_space == gymnasium.spaces.Discrete(2)
    assert v.action_space.shape == (N,) and v.observation_space.shape == (N, 4)
    assert v.single_observation_space.dtype == np.float32
    o1, info = v.reset(seed=3)
    assert o1 in v.observation_space and info == {}  # render=False: no frames to put in info
    np.testing.assert_array_equal(o1, np.asarray(cartpole.reset(jax.random.PRNGKey(3)).lowdim))
    traj1 = [v.step(v.action_space.sample())[0] for _ in range(3)]
    o2, _ = v.reset(seed=3)
    np.testing.assert_array_equal(o1, o2)
    o3, _ = v.reset(seed=4)
    assert not np.allclose(o1, o3)
    v.reset(seed=11)
    u1 = v.reset()[0]
    v.reset(seed=11)
    np.testing.assert_array_equal(u1, v.reset()[0])  # unseeded resets follow the last seed
    with pytest.raises(ValueError, match="integer actions"):
        v.step(np.zeros((N, 2), np.int64))
    with pytest.raises(ValueError, match=r"in \[0, 2\)"):
        v.step(np.full(N, 2))
    with pytest.raises(ValueError, match="one int seed"):
        v.reset(seed=[1, 2, 3, 4])
    with pytest.raises(ValueError, match="obs must be one of"):
        make_vec("CartPole", 2, obs="latent")
    with pytest.raises(ValueError, match="autoreset_mode"):
        make_vec("CartPole", 2, autoreset_mode="disabled")
    with pytest.raises(ValueError, match='obs="pixels" needs'):
        BulbjaxVectorEnv(cartpole, obs="pixels")
    # partial reset: only the masked worlds restart
    v.reset(seed=5)
    before = v.step(ACTIONS)[0]
    mask = np.array([True, False, False, False])
    after, _ = v.reset(seed=6, options={"reset_mask": mask})
    np.testing.assert_array_equal(after[1:], before[1:])
    np.testing.assert_array_equal(after[0], np.asarray(cartpole.reset(jax.random.PRNGKey(6)).lowdim[0]))
    assert len(traj1) == 3


def test_vector_pixels_last_frame():
    """obs="pixels": frames uint8, state in info; the last frame of an ended episode is the frame
    of the state before the reset (the replayed physics step renders what `step` renders)."""
    v = make_vec("CartPole", 2, obs="pixels", resolution=32)
    obs, info = v.reset(seed=0)
    assert obs.dtype == np.uint8 and obs.shape == (2, 32, 32, 3) and obs in v.observation_space
    assert info["state"].shape == (2, 4) and info["_state"].all()
    a = np.ones(2, np.int64)
    ended = checked_live = False
    for _ in range(15):
        prev = v.state
        obs, rew, term, trunc, info = v.step(a)
        last = jax.device_get(v.core.last(prev, v.core.action(a)))
        live = ~(term | trunc)
        # worlds that did not end: the replay reproduces the step's frame and state
        if live.any():
            assert np.abs(last["pixels"][live].astype(int) - obs[live].astype(int)).mean() < 0.5
            np.testing.assert_allclose(last["state"][live], info["state"][live], atol=1e-6)
            checked_live = True
        if (~live).any():
            np.testing.assert_array_equal(obs[~live], last["pixels"][~live])
            np.testing.assert_allclose(info["state"][~live], last["state"][~live], atol=1e-6)
            reset_frames = np.asarray(v.state.pixels)[~live]
            assert np.abs(reset_frames.astype(int) - obs[~live].astype(int)).max() > 0  # new episode differs
            nxt, rew2, *_ = v.step(a)
            np.testing.assert_array_equal(nxt[~live], reset_frames)  # next_step: the reset frame
            assert (rew2[~live] == 0).all()
            ended = True
            break
    assert ended and checked_live


def test_gymnasium_make_after_import():
    """`import bulbjax.gym` (done above) registered the ids: gymnasium.make builds the env with its
    spec, and check_env passes without gymnasium's warning about a missing spec."""
    import warnings

    env = gymnasium.make("bulbjax/CartPole-v0", obs="pixels", resolution=32)
    assert env.spec is not None and env.spec.id == "bulbjax/CartPole-v0"
    assert env.spec.max_episode_steps == 200  # the domain's episode length (issue 58: None)
    assert gymnasium.spec("bulbjax/InvertedPendulumMulticolour-v0").max_episode_steps == 1000
    assert env.unwrapped.observation_space.shape == (32, 32, 3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_close_check=True)
    assert not [w for w in caught if "spec" in str(w.message).lower()], [str(w.message) for w in caught]


def test_single_env_check_env():
    env = make_env("CartPoleContinuous", obs="pixels", resolution=32, render_mode="rgb_array")
    assert isinstance(env, GymEnv)
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    assert env.observation_space.dtype == np.uint8 and env.observation_space.shape == (32, 32, 3)
    check_env(env, skip_close_check=True)
    obs, info = env.reset(seed=1)
    assert info["state"].shape == (4,) and env.render().shape == (32, 32, 3)
    env.render_mode = None  # as made without render_mode: None, and a warning saying how (issue 58)
    with pytest.warns(UserWarning, match=r'render_mode="rgb_array"'):
        assert env.render() is None
    env.render_mode = "rgb_array"
    with pytest.raises(ValueError, match="action of shape"):
        env.step(np.zeros(3, np.float32))
    total, terminated, truncated = 0.0, False, False
    while not (terminated or truncated):
        obs, r, terminated, truncated, info = env.step(np.ones(1, np.float32))
        total += r
    assert obs in env.observation_space and info["episode_return"] == total
    assert abs(info["state"][0]) > env.bulbjax_env.theta_threshold or abs(info["state"][2]) > 0.4
    with pytest.raises(ValueError, match="num_envs=1"):
        GymEnv(bulbjax.make("CartPole", num_envs=2, render=False), obs="state")


def test_brax_wrapper_under_jit(cartpole):
    """Runs with or without Brax installed (without it, a stand-in State of the same fields)."""
    from bulbjax.interop.brax import HAVE_BRAX, State

    env = BraxEnv(cartpole)
    if HAVE_BRAX:
        import brax.envs.base as brax_base

        assert isinstance(env, brax_base.Env) and State is brax_base.State
    assert (env.observation_size, env.action_size, env.backend) == (4, 2, "mjx")
    key = jax.random.PRNGKey(2)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    s = reset(jax.random.split(key, N).at[0].set(key))  # Brax's batch of keys: the first seeds all
    ref = jax.jit(cartpole.reset)(key)
    np.testing.assert_array_equal(s.obs, ref.lowdim)
    assert isinstance(s, State) and s.info["truncation"].shape == (N,)
    one_hot = jax.nn.one_hot(ACTIONS, 2)  # discrete: argmax of each row
    ref_step = jax.jit(cartpole.step)
    s = s.replace(info={**s.info, "outer": jnp.zeros(N)})  # entries of outer wrappers are kept
    seen_done = False
    for _ in range(EP_LEN + 2):
        s, ref = step(s, one_hot), ref_step(ref, jnp.asarray(ACTIONS))
        np.testing.assert_array_equal(s.obs, ref.lowdim)
        np.testing.assert_array_equal(s.reward, ref.reward)
        np.testing.assert_array_equal(s.done, ref.done)
        np.testing.assert_array_equal(s.info["truncation"], ref.truncated)
        done = np.asarray(ref.done) > 0
        em = s.info["episode_metrics"]
        np.testing.assert_array_equal(np.asarray(em["sum_reward"])[done], np.asarray(ref.info["episode_return"])[done])
        np.testing.assert_array_equal(np.asarray(s.info["steps"])[done], np.asarray(ref.info["episode_length"])[done])
        assert "outer" in s.info
        seen_done |= done.any()
    assert seen_done
    with pytest.raises(ValueError, match="actions of shape"):
        step(s, jnp.zeros((N, 1)))
    with pytest.raises(ValueError, match="batch of 3 keys"):
        env.reset(jax.random.split(key, 3))
    with pytest.raises(ValueError, match="obs must be one of"):
        BraxEnv(cartpole, obs="latent")


def test_brax_unroll_with_brax_acting(cartpole):
    """Brax's own unroll (what its PPO calls) reads the wrapper's extras."""
    acting = pytest.importorskip("brax.training.acting")
    env = BraxEnv(cartpole)
    policy = lambda obs, key: (jnp.tile(jnp.array([0.0, 1.0]), (obs.shape[0], 1)), {})

    @jax.jit
    def unroll(key):
        s = env.reset(key)
        return acting.generate_unroll(env, s, policy, key, 6,
                                      extra_fields=("truncation", "episode_metrics", "episode_done"))

    _, data = unroll(jax.random.PRNGKey(0))
    assert data.observation.shape == (6, N, 4) and data.action.shape == (6, N, 2)
    extras = data.extras["state_extras"]
    assert extras["truncation"].shape == (6, N) and extras["episode_metrics"]["sum_reward"].shape == (6, N)
    # pushing right every step accumulates one reward per step until an episode ends
    np.testing.assert_array_equal(np.asarray(extras["episode_metrics"]["length"])[:, 0], np.arange(1, 7))


def test_register_envs():
    from bulbjax.gym import register_envs

    ids = register_envs()
    assert "bulbjax/CartPole-v0" in ids and len(ids) == len(bulbjax.env_names())
    spec = gymnasium.spec("bulbjax/InvertedPendulumMulticolour-v0")
    assert spec.vector_entry_point is not None and spec.nondeterministic is False
    # gymnasium.make_vec hands the spec's max_episode_steps to the vector entry point
    venv = gymnasium.make_vec("bulbjax/CartPole-v0", num_envs=2,
                              vectorization_mode="vector_entry_point", obs="state", render=False)
    assert isinstance(venv, BulbjaxVectorEnv) and venv.num_envs == 2
    with pytest.raises(ValueError, match="truncate episodes at the domain's 200 steps"):
        gymnasium.make_vec("bulbjax/CartPole-v0", num_envs=2, vectorization_mode="vector_entry_point",
                           obs="state", render=False, max_episode_steps=50)


def test_importing_interop_gym_registers(tmp_path):
    """`import bulbjax.interop.gym` registers as `import bulbjax.gym` does (issue 58: only the
    latter did, though the docs call them the same module)."""
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import gymnasium\nimport bulbjax.interop.gym\nimport sys\n"
            "assert 'bulbjax.gym' not in sys.modules\n"
            "print(sorted(i for i in gymnasium.registry if i.startswith('bulbjax/'))[:1])\n")
    env = {**os.environ, "PYTHONPATH": root}
    r = subprocess.run([sys.executable, "-c", code], cwd=str(tmp_path), env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "bulbjax/Ant-v0" in r.stdout


def _brax_snippet(num_envs: int) -> str:
    """docs/interop.md's Brax snippet (the first python block of its Brax section), with
    `num_envs` worlds for its 1024."""
    import os
    import re

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open(os.path.join(root, "docs", "interop.md"), encoding="utf-8") as f:
        section = f.read().split("## Brax and MuJoCo Playground", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "1024" in code and "benv.step" in code, code
    return code.replace("1024", str(num_envs))


def test_brax_snippet_exits(tmp_path):
    """docs/interop.md's Brax snippet, run as a script with Brax installed, prints its shapes and
    exits (issue 65: it printed them, then hung in the interpreter's final garbage collection: the
    step still running called Warp's GIL-taking callback after Python began finalising). Whether
    its one step is still running at the end depends on timing, so the script then dispatches 200
    steps and ends without waiting for them: that hung every time. Brax is in the test extra, so
    `make test` runs this."""
    import os
    import subprocess
    import sys

    pytest.importorskip("brax", reason="brax is in the test extra (pyproject.toml): pip install -e '.[test]'")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = _brax_snippet(16) + (
        "import brax.envs.base\n"
        "assert isinstance(state, brax.envs.base.State), type(state)\n"
        "zeros = jnp.zeros((16, benv.action_size))\n"
        "state = jax.jit(lambda s: jax.lax.fori_loop(0, 200, lambda i, s: benv.step(s, zeros), s))(state)\n"
        "print('dispatched', flush=True)\n")  # and the script ends with them running
    script = tmp_path / "brax_snippet.py"
    script.write_text(code)
    env = {**os.environ, "PYTHONPATH": root}
    try:  # ~20 s on 2 CPU cores (importing brax ~6 s); a hang is what this catches
        r = subprocess.run([sys.executable, str(script)], cwd=str(tmp_path), env=env, capture_output=True,
                           text=True, timeout=180)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"the Brax snippet did not exit within {e.timeout} s; it printed {e.stdout!r}")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "(16, 4) (16,)" in r.stdout and "dispatched" in r.stdout, r.stdout
