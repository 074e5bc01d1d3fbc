"""XLA compile options as `bulbjax run --xla-option` and the benchmarks read them: `KEY=VALUE`
strings to the dict `jax.jit(...).lower(...).compile(compiler_options=...)` takes. A module of its
own, below the experiment package, so that the learner benchmarks read options without loading
the environments."""

from __future__ import annotations

from typing import Any, Sequence


def parse_compiler_options(items: Sequence[str]) -> dict[str, Any]:
    """`["KEY=VALUE", ...]` -> XLA compile options for `jax.jit(..., compiler_options=...)`: values
    that read as ints, floats or true/false become those, the rest stay strings (e.g.
    `xla_gpu_enable_command_buffer=FUSION,CUBLAS,WHILE`). XLA rejects unknown keys at compile."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"compiler option {item!r} must read KEY=VALUE, e.g. "
                             "xla_gpu_enable_command_buffer=FUSION,CUBLAS,WHILE")
        value: Any = text.strip()
        if value.lower() in ("true", "false"):
            value = value.lower() == "true"
        else:
            for cast in (int, float):
                try:
                    value = cast(value)
                    break
                except ValueError:
                    pass
        out[key.strip()] = value
    return out


def parse_named_options(text: str) -> tuple[str, dict[str, Any]]:
    """`NAME=KEY:VALUE;KEY:VALUE` (or a bare `NAME`, no options) -> (NAME, compile options), the
    form in which the benchmarks take sets of XLA options to time side by side. The sets arrive
    comma-separated, so a `+` in a VALUE stands for a comma in the option's list (e.g.
    `cb=xla_gpu_enable_command_buffer:FUSION+CUBLAS+WHILE`)."""
    name, _, rest = text.partition("=")
    return name, parse_compiler_options([kv.replace(":", "=", 1).replace("+", ",")
                                         for kv in rest.split(";") if kv])
