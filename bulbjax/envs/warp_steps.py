"""An env step's physics substeps as one MuJoCo Warp call.

Why: every MJX-Warp operation is a `warp.jax_callable`, and each call costs the host a ctypes
callback under the GIL that reads every buffer's address (MJX's step passes ~470 buffers) to find
its captured CUDA graph. A locomotion env step is `frame_skip` = 4 `mjx.step` calls and a
`mjx.kinematics` call: five callbacks for ~0.3 ms of small kernels each. One call per env step
took a HalfCheetah epoch on one H200 from 1.785 s to 1.726 s (-3.3%, ~56 us per callback saved):
the callbacks are not what bounds PPO's phase, the graphs' chains of small kernels are
(docs/performance.md, "The locomotion epoch").

`multi_step(n, kinematics)` is `mjx.step` applied `n` times (and `mjx.kinematics` after, when
asked) as one callable: MJX's own generated step, with the single `mujoco_warp.step` call in its
body replaced by `n` of them (and the kinematics). The kernels, their order and their buffers are
those of the separate calls, so the result is the same bit for bit (`tests/test_warp_steps.py`, on
the CPU's Warp); one CUDA graph replays all of them per env step. It holds only where nothing
changes between substeps but the physics: the action is the same controls at every substep
(`MjxPixelEnv._apply_action`'s default), which `MjxPixelEnv.physics` checks before using it.

It builds on MJX-Warp's generated module (`mujoco.mjx.warp.forward._step_shim` and
`_step_jax_impl`, MuJoCo MJX 3.17): `available()` says whether this MJX has that shape, and the
environments fall back to the separate calls where it does not.
"""

from __future__ import annotations

import functools
import types
from typing import Any, Callable

import jax

_SHIM = "_step_shim"
_IMPL = "_step_jax_impl"


@functools.cache
def available() -> bool:
    """Whether this MJX's Warp step has the generated shape `multi_step` rewrites."""
    try:
        from mujoco.mjx.warp import ffi, forward  # noqa: F401
    except ImportError:
        return False
    shim = getattr(forward, _SHIM, None)
    impl = getattr(forward, _IMPL, None)
    inner = getattr(shim, "__wrapped__", None)
    return (inner is not None and impl is not None and "mjwarp" in inner.__code__.co_names
            and _SHIM in impl.__code__.co_names and hasattr(ffi, "marshal_custom_vmap"))


class _Substeps:
    """Stands in for the `mujoco_warp` module inside a copy of MJX's step shim: its `step` runs
    `n` steps (then the kinematics), every other name is the module's."""

    def __init__(self, module: Any, n: int, kinematics: bool):
        self._module, self._n, self._kinematics = module, n, kinematics

    def __getattr__(self, name: str) -> Any:
        return getattr(self._module, name)

    def step(self, m: Any, d: Any) -> None:
        for _ in range(self._n):
            self._module.step(m, d)
        if self._kinematics:
            self._module.kinematics(m, d)


def _with_globals(fn: Callable[..., Any], name: str, **replace: Any) -> Callable[..., Any]:
    """A copy of the plain function `fn` whose global names in `replace` are rebound."""
    scope = dict(fn.__globals__, **replace)
    out = types.FunctionType(fn.__code__, scope, name, fn.__defaults__, fn.__closure__)
    out.__annotations__ = dict(fn.__annotations__)
    out.__kwdefaults__ = fn.__kwdefaults__
    out.__module__ = fn.__module__
    out.__qualname__ = name
    return out


@functools.cache
def multi_step(n: int, kinematics: bool) -> Callable[[Any, Any], Any]:
    """`mjx.step` `n` times (then `mjx.kinematics` if `kinematics`) as one MJX-Warp call;
    `(model, data) -> data`, vmappable over `data` as `mjx.step` is."""
    if n < 1:
        raise ValueError(f"multi_step needs at least one substep, got {n}")
    if not available():
        raise RuntimeError("this MuJoCo MJX has no generated Warp step to fuse substeps into "
                           "(mujoco.mjx.warp.forward._step_shim); use the separate calls")
    from mujoco.mjx.warp import ffi, forward

    tag = f"_step{n}{'k' if kinematics else ''}"
    inner = forward._step_shim.__wrapped__
    substeps = _Substeps(inner.__globals__["mjwarp"], n, kinematics)
    shim = ffi.format_args_for_warp(_with_globals(inner, tag + "_shim", mjwarp=substeps))
    impl = _with_globals(forward._step_jax_impl, tag + "_jax_impl", **{_SHIM: shim})

    @jax.custom_batching.custom_vmap
    @ffi.marshal_jax_warp_callable
    def step(m: Any, d: Any) -> Any:
        return impl(m, d)

    @step.def_vmap
    @ffi.marshal_custom_vmap
    def step_vmap(axis_size: int, is_batched: Any, m: Any, d: Any) -> tuple[Any, Any]:
        return step(m, d), is_batched[1]

    return step
