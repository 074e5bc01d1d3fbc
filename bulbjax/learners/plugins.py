"""Learners of one's own, named where learner names are taken (`bulbjax run --learners`, `fit`,
`ExperimentConfig.learners`), with no edit of bulbjax: how a spec is read, imported and
registered, and how an installed package offers its learners.

A spec, as the Python ecosystem writes an object reference (entry points, `module:attr`):
- `MODULE:ATTR`: import MODULE (from `sys.path`: PYTHONPATH, the working directory of
  `python -m`, an installed package), then take its ATTR:
  - a factory or class the import registered (`register_learner`, e.g. as a decorator): its
    registered name;
  - a class with `init`, `update` and `encode` (the `FrameLearner` / `SequenceLearner`
    protocols, `bulbjax/learners/base.py`) or a factory `(latent_dim, config, action_dim) ->
    learner` that nobody registered: registered here under ATTR (a class gets `latent_dim`,
    `config` and `action_dim` where its constructor takes them; `sequential` from the class);
  - where the module has no ATTR, a learner its import registered under the name ATTR.
- `PATH.py:ATTR`: the same from a file (a path with `/` or ending in `.py`; relative to the
  working directory, recorded absolute), imported as a module of its own.
- `NAME=MODULE:ATTR` (either form): registered under NAME instead of ATTR.
- an installed package's learners: entry points of group `bulbjax.learners` (`name =
  "module:attr"` in its pyproject.toml's `[project.entry-points."bulbjax.learners"]`); the bare
  name then works (`--learners name`), loaded as `name=module:attr` at first use.

`load_learner_spec(spec)` imports and registers once per process (a second call returns the same
name), and checks the whole protocol the experiment relies on (`FrameLearner` / `SequenceLearner`,
the members docs/extending.md lists as required) on a learner built from the factory with sample
arguments, so that a missing member is one line naming it before any run folder, environment or
program is made, not a traceback after tracing. A run records the specs of the learners it was given this way in its config
(`ExperimentConfig.learner_modules`), so that `bulbjax report`, `recon` and `run --resume` load
them again with no flag; a spec that no longer loads is then a one-line error naming it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import os
import re
import sys
from typing import Any

from bulbjax.learners.base import LearnerConfig
from bulbjax.learners.registry import _REGISTRY, Registration, register_learner

ENTRY_POINT_GROUP = "bulbjax.learners"
_PROTOCOL = ("init", "update", "encode")
# What the experiment reads of every learner (docs/extending.md's table, `FrameLearner`), and
# besides of a sequential one (`SequenceLearner`); the methods must be callable.
FRAME_MEMBERS: tuple[str, ...] = ("latent_dim", "config", "retain_fraction", "batch_size", *_PROTOCOL)
SEQUENCE_MEMBERS: tuple[str, ...] = (*FRAME_MEMBERS, "action_dim", "sequence_length", "window_length")
_LOADED: dict[str, str] = {}  # canonical spec -> the name it registered
_PROVIDER: dict[str, str] = {}  # learner name -> the first spec whose loading registered it


class LearnerLoadError(ValueError):
    """A learner spec that cannot be loaded: a module that does not import, a missing ATTR, an
    object that is no learner, a name taken by another learner. One line, naming the spec."""


def is_spec(item: str) -> bool:
    """Whether a `--learners` item is a spec (`[NAME=]MODULE:ATTR`, `[NAME=]PATH.py:ATTR`) rather
    than a learner name (names have no ':')."""
    return ":" in item


def _split(spec: str) -> tuple[str | None, str, str]:
    """(NAME or None, MODULE or PATH, ATTR) of a spec."""
    name = None
    head, eq, rest = spec.partition("=")
    if eq and ":" not in head and "/" not in head and os.sep not in head:
        name, spec = head.strip(), rest
    target, colon, attr = spec.strip().rpartition(":")
    if not colon or not target.strip() or not attr.strip():
        raise LearnerLoadError(f"learner {spec!r} must read MODULE:NAME or path/to/file.py:NAME "
                               "(optionally NEWNAME=MODULE:NAME)")
    return name, target.strip(), attr.strip()


def _is_file(target: str) -> bool:
    return target.endswith(".py") or "/" in target or os.sep in target


def canonical_spec(spec: str) -> str:
    """The spec as a config records it: a file's path made absolute (so that `report` and
    `--resume` from another folder find it), whitespace dropped."""
    name, target, attr = _split(spec)
    if _is_file(target):
        target = os.path.abspath(os.path.expanduser(target))
    return f"{name + '=' if name else ''}{target}:{attr}"


def _loaded_from(path: str) -> Any:
    """A module already imported from the file `path`, or None: a file named by its path and by
    its module name is one module, imported (and registering its learners) once."""
    real = os.path.realpath(path)
    for module in list(sys.modules.values()):
        file = getattr(module, "__file__", None)
        if file and os.path.realpath(file) == real:
            return module
    return None


def _import(spec: str, target: str) -> Any:
    """The module of `target` (a dotted module or a file), imported once."""
    try:
        if not _is_file(target):
            if target in sys.modules:
                return sys.modules[target]
            found = importlib.util.find_spec(target)
            same = _loaded_from(found.origin) if found is not None and found.origin else None
            if same is not None:
                sys.modules[target] = same
                return same
            return importlib.import_module(target)
        if not os.path.isfile(target):
            raise LearnerLoadError(f"learner {spec!r}: no such file {target!r}")
        same = _loaded_from(target)
        if same is not None:
            return same
        stem = re.sub(r"\W", "_", os.path.splitext(os.path.basename(target))[0])
        module_name = f"bulbjax_learner_{stem}_{hashlib.sha1(target.encode()).hexdigest()[:8]}"
        if module_name in sys.modules:
            return sys.modules[module_name]
        found = importlib.util.spec_from_file_location(module_name, target)
        module = importlib.util.module_from_spec(found)
        sys.modules[module_name] = module  # dataclasses look their module up while it runs
        try:
            found.loader.exec_module(module)
        except BaseException:
            del sys.modules[module_name]
            raise
        return module
    except LearnerLoadError:
        raise
    except Exception as err:  # noqa: BLE001 - whatever the import raised, said in one line
        why = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}".rstrip(": ")
        hint = ""
        if isinstance(err, ModuleNotFoundError) and not _is_file(target) and err.name and \
                target.split(".")[0] == err.name.split(".")[0]:
            hint = "; put its folder on PYTHONPATH (or install its package)"
        raise LearnerLoadError(f"learner {spec!r}: cannot import {target!r} ({why}){hint}") from err


def _registered_as(obj: Any) -> list[Registration]:
    return [r for r in _REGISTRY.values()
            if r.factory is obj or getattr(r.factory, "__wrapped__", None) is obj]


def _class_factory(cls: type) -> Any:
    """A factory `(latent_dim, config, action_dim)` of a learner class: the arguments its
    constructor takes, by name."""
    params = inspect.signature(cls).parameters
    takes = [n for n in ("latent_dim", "config", "action_dim") if n in params]

    def make(latent_dim: int, config: Any, action_dim: int) -> Any:
        given = {"latent_dim": latent_dim, "config": config, "action_dim": action_dim}
        return cls(**{n: given[n] for n in takes})

    make.__wrapped__ = cls  # type: ignore[attr-defined]
    make.__name__ = f"make_{cls.__name__}"
    return make


def _takes_three(fn: Any) -> bool:
    try:
        inspect.signature(fn).bind(1, None, 1)
        return True
    except (TypeError, ValueError):
        return False


def _register(spec: str, name: str, obj: Any) -> str:
    """Register `obj` (a learner class or factory nobody registered) as `name`."""
    if inspect.isclass(obj):
        missing = [m for m in _PROTOCOL if not callable(getattr(obj, m, None))]
        if missing:
            raise LearnerLoadError(f"learner {spec!r}: class {obj.__name__} is no learner: it lacks "
                                   f"{', '.join(missing)} (FrameLearner / SequenceLearner, "
                                   "bulbjax/learners/base.py)")
        factory = _class_factory(obj)
    elif callable(obj) and _takes_three(obj):
        factory = obj
    else:
        raise LearnerLoadError(f"learner {spec!r}: {type(obj).__name__} {obj!r:.60} is neither a "
                               "learner class (with init, update, encode) nor a factory (latent_dim, "
                               "config, action_dim)")
    if name in _REGISTRY:
        raise LearnerLoadError(f"learner {spec!r}: the name {name!r} is another learner's; give "
                               f"this one another name: OTHERNAME={spec.split('=', 1)[-1]}")
    try:
        register_learner(name, factory, sequential=getattr(obj, "sequential", None))
    except ValueError as err:
        raise LearnerLoadError(f"learner {spec!r}: {err}") from err
    return name


def load_learner_spec(spec: str) -> str:
    """Import and register the learner of `spec` (the module doc's forms); returns its registered
    name, the one `ExperimentConfig.learners` takes. Idempotent: a spec loaded before returns
    the same name. A spec that cannot be loaded is a `LearnerLoadError` (a ValueError, one line)."""
    key = canonical_spec(spec)
    if key in _LOADED and _LOADED[key] in _REGISTRY:
        return _LOADED[key]
    before = set(_REGISTRY)
    try:
        got = _load(key)
        try:
            check_protocol(key, _REGISTRY[got])
        except LearnerLoadError:
            for new in set(_REGISTRY) - before:  # no learner short of the protocol stays registered
                del _REGISTRY[new]
            raise
    finally:
        for new in set(_REGISTRY) - before:  # every learner this spec's import registered
            _PROVIDER.setdefault(new, key)
    _PROVIDER.setdefault(got, key)  # also where the caller imported the module before
    _LOADED[key] = got
    return got


def _missing(learner: Any, members: tuple[str, ...]) -> list[str]:
    """The `members` `learner` lacks (looked up without running a property: a property present
    counts, whatever it would compute), or has but cannot call where a method is required."""
    absent = object()
    out = []
    for m in members:
        found = inspect.getattr_static(learner, m, absent)
        if found is absent or (m in _PROTOCOL and not callable(getattr(learner, m, None))):
            out.append(m)
    return out


def check_protocol(spec: str, reg: Registration) -> None:
    """Refuse, in one line, a learner of `spec` that lacks a member the experiment reads
    (`FRAME_MEMBERS`, or `SEQUENCE_MEMBERS` for a sequential one): checked on a learner built by
    its factory with sample arguments (a frozen dataclass is cheap to build; nothing is traced).
    A factory that cannot be called so is left to the run (its own error then); a class whose
    constructor fails is checked on the class (its attributes, fields and annotations)."""
    made = getattr(reg.factory, "__wrapped__", reg.factory)
    try:
        learner = reg.factory(2, LearnerConfig(**dict(reg.defaults)), 1)
    except Exception:  # noqa: BLE001 - only the members are checked here
        if not inspect.isclass(made):
            return
        learner = made
    sequential = reg.sequential or bool(getattr(learner, "sequential", False))
    members = SEQUENCE_MEMBERS if sequential else FRAME_MEMBERS
    if inspect.isclass(learner):  # fields and annotated attributes are not on the class itself
        known = set(dir(learner))
        if dataclasses.is_dataclass(learner):
            known |= {f.name for f in dataclasses.fields(learner)}
        for klass in learner.__mro__:
            known |= set(getattr(klass, "__annotations__", {}))
        missing = [m for m in members if m not in known]
    else:
        missing = _missing(learner, members)
    if missing:
        kind, protocol = (("sequential learner", "SequenceLearner") if sequential
                          else ("frame learner", "FrameLearner"))
        what = made.__name__ if inspect.isclass(made) else type(learner).__name__
        raise LearnerLoadError(
            f"learner {spec!r}: {what} is no {kind}: it lacks {', '.join(missing)}; add them as "
            f"docs/extending.md's 'A new learner' lists ({protocol}, bulbjax/learners/base.py)")


def _belongs(reg: Registration, module: Any) -> bool:
    """Whether a registration's factory (or the class it wraps) is defined in `module`."""
    made = getattr(reg.factory, "__wrapped__", reg.factory)
    return getattr(made, "__module__", None) == module.__name__


def _load(key: str) -> str:
    name, target, attr = _split(key)
    module = _import(key, target)
    if not hasattr(module, attr):
        if attr in _REGISTRY and name in (None, attr) and _belongs(_REGISTRY[attr], module):
            return attr  # a name its import registered (a built-in `vae` is nobody's plugin)
        learners = sorted(n for n, v in vars(module).items() if not n.startswith("_")
                          and inspect.isclass(v)
                          and all(callable(getattr(v, m, None)) for m in _PROTOCOL))
        has = f"; it has the learner classes {', '.join(learners)}" if learners else ""
        raise LearnerLoadError(f"learner {key!r}: {target} has no {attr!r}{has}")
    obj = getattr(module, attr)
    regs = _registered_as(obj)
    if name is None and len(regs) == 1:
        got = regs[0].name
    elif name is None and regs:
        names = [r.name for r in regs]
        if attr not in names:
            raise LearnerLoadError(f"learner {key!r}: {attr} is registered as {', '.join(names)}: "
                                   f"name one, e.g. {names[0]}={key}")
        got = attr
    elif name is not None and name in {r.name for r in regs}:
        got = name
    elif regs:  # registered under other names: the same learner under this one too
        first = regs[0]
        if name in _REGISTRY:
            raise LearnerLoadError(f"learner {key!r}: the name {name!r} is another learner's")
        register_learner(name, first.factory, defaults=first.defaults, sequential=first.sequential,
                         frame_latent=first.frame_latent)
        got = name
    else:
        got = _register(key, name or attr, obj)
    return got


def spec_of(name: str) -> str | None:
    """The spec whose loading registered learner `name` in this process (what a config records
    to find it again), or None (a built-in learner, or one registered by a caller's own code)."""
    return _PROVIDER.get(name)


def entry_point_spec(name: str) -> str | None:
    """The spec (`name=module:attr`) of an installed package's learner `name` (entry point group
    `bulbjax.learners`), or None."""
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == name:
            return f"{ep.name}={ep.value}"
    return None


def parse_learner_list(items: Any) -> tuple[str, ...]:
    """The learner names of `--learners`' items (a comma-separated text or a sequence): a
    registered name as it is; a spec loaded (its registered name); an unknown name that an
    installed package offers (entry points) loaded likewise. Unknown names stay (the config
    names them in its error)."""
    if isinstance(items, str):
        items = [x.strip() for x in items.split(",") if x.strip()]
    names = []
    for item in items:
        spec = item if is_spec(item) else None if item in _REGISTRY else entry_point_spec(item)
        names.append(item if spec is None else load_learner_spec(spec))
    return tuple(names)
