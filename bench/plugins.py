"""Method registry: in-repo methods (each folder under methods/ whose package exports
`METHOD`) plus third-party methods from the entry-point group `ildbench.methods`.

A third-party package adds, in its pyproject.toml:

    [project.entry-points."ildbench.methods"]
    mymethod = "mypkg.mymethod:METHOD"      # a bench.api.MethodSpec

Duplicate names raise. bench/ never imports a concrete method by name: only through here.
"""
from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import typing
from importlib import metadata
from typing import Any, Mapping

from bench.api import MethodSpec

ENTRY_POINT_GROUP = "ildbench.methods"


class UnknownMethodError(KeyError):
    def __str__(self) -> str:
        return str(self.args[0])


class ConfigError(ValueError):
    pass


class MethodUnavailableError(UnknownMethodError):
    """An in-repo method whose third-party dependency is not installed."""


_REGISTRY: dict[str, MethodSpec] = {}
_SOURCES: dict[str, str] = {}
_UNAVAILABLE: dict[str, str] = {}  # in-repo method folder -> the missing dependency's error
_loaded = False
_OWN_PACKAGES = ("bench", "methods", "tasks")


def register(spec: MethodSpec, source: str = "in-repo") -> MethodSpec:
    if not isinstance(spec, MethodSpec):
        raise TypeError(f"{source}: expected a bench.api.MethodSpec, got {type(spec).__name__}")
    if spec.name in _REGISTRY:
        raise ValueError(f"method {spec.name!r} is registered twice ({_SOURCES[spec.name]} and "
                         f"{source}); rename one of them")
    if not (dataclasses.is_dataclass(spec.config_cls)
            and spec.config_cls.__dataclass_params__.frozen):
        raise TypeError(f"method {spec.name!r}: config_cls must be a frozen dataclass")
    if spec.min_env_steps is not None and not (isinstance(spec.min_env_steps, int)
                                               and spec.min_env_steps >= 1):
        raise ValueError(f"method {spec.name!r}: min_env_steps must be a whole number >= 1 "
                         f"or None, got {spec.min_env_steps!r}")
    # checked here, not where they apply: another platform's overrides never run on this one
    fields = [f.name for f in dataclasses.fields(spec.config_cls)]
    for platform, per_task in spec.platform_overrides.items():
        for task, over in per_task.items():
            unknown = sorted(set(over) - set(fields))
            if unknown:
                raise ConfigError(f"method {spec.name!r}: platform_overrides[{platform!r}]"
                                  f"[{task!r}] names no config field {unknown}; fields: "
                                  f"{', '.join(fields)}")
    _REGISTRY[spec.name] = spec
    _SOURCES[spec.name] = source
    return spec


def _load_all() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    import methods
    for info in pkgutil.iter_modules(methods.__path__):
        if not info.ispkg or info.name.startswith("_") or info.name == "common":
            continue
        try:
            module = importlib.import_module(f"methods.{info.name}")
        except ModuleNotFoundError as e:
            # A missing third-party package (e.g. gymnasium for DAC on a machine that only
            # has the JAX stack) leaves the other methods usable; asking for this one then
            # names what is missing. A module of our own missing is a bug: re-raise.
            if (e.name or "").split(".")[0] in _OWN_PACKAGES:
                raise
            _UNAVAILABLE[info.name] = f"{e}"
            continue
        # A folder is one method (METHOD) or a family sharing code (METHODS).
        for spec in getattr(module, "METHODS", None) or [getattr(module, "METHOD", None)]:
            if spec is not None:
                register(spec, source=f"methods/{info.name}")
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.value.startswith("methods."):  # our own methods, if the install lists them
            continue
        register(ep.load(), source=f"entry point {ep.name} = {ep.value}")


def all_methods() -> dict[str, MethodSpec]:
    _load_all()
    return dict(_REGISTRY)


def get_method(name: str) -> MethodSpec:
    methods_ = all_methods()
    if name not in methods_ and name in _UNAVAILABLE:
        raise MethodUnavailableError(
            f"method {name!r} cannot be loaded here: {_UNAVAILABLE[name]}; install the "
            f"project's dependencies (pip install -e .) or pick another method; loadable "
            f"methods: {', '.join(sorted(methods_))}")
    if name not in methods_:
        missing = "".join(f"; methods/{k} not loadable here: {v}"
                          for k, v in sorted(_UNAVAILABLE.items()))
        raise UnknownMethodError(
            f"unknown method {name!r}; valid methods: {', '.join(sorted(methods_))}{missing}")
    return methods_[name]


def _coerce(field: dataclasses.Field, hint, value: Any, method: str) -> Any:
    """CLI overrides arrive as strings; turn them into the field's type."""
    if not isinstance(value, str):
        return value
    origin = typing.get_origin(hint)
    try:
        if hint is bool:
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if hint in (int, float, str):
            return hint(value)
        if origin is tuple:
            inner = typing.get_args(hint)[0]
            return tuple(inner(v) for v in value.strip("()[] ").split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"method {method!r}: config field {field.name!r} expects "
                          f"{getattr(hint, '__name__', hint)}, got {value!r}") from None
    return value


def current_platform() -> str:
    """The platform JAX computes on here: 'cpu', 'gpu' or 'tpu' (`jax.default_backend()`)."""
    import jax
    return jax.default_backend()


def build_config(spec: MethodSpec, task: str, preset: str | None = None,
                 overrides: Mapping[str, Any] | None = None, platform: str | None = None):
    """defaults (the paper's) <- per-task overrides <- the platform's per-task overrides
    (`platform`, default `current_platform()` where the spec has any) <- preset <- user
    overrides; a task override whose `spec.requires` field a later layer turns off is
    dropped."""
    fields = {f.name: f for f in dataclasses.fields(spec.config_cls)}
    hints = typing.get_type_hints(spec.config_cls)
    if preset is not None and preset not in spec.presets:
        raise ConfigError(f"method {spec.name!r} has no preset {preset!r}; presets: "
                          f"{', '.join(sorted(spec.presets)) or 'none'}")
    merged: dict[str, Any] = {}
    layer_of: dict[str, int] = {}  # the last layer that set each field (0: the task's)
    if platform is None and spec.platform_overrides:
        platform = current_platform()
    on_platform = spec.platform_overrides.get(platform, {}).get(task, {})
    layers = [spec.task_overrides.get(task, {}), on_platform,
              spec.presets.get(preset, {}) if preset else {}, overrides or {}]
    for i, layer in enumerate(layers):
        for k, v in layer.items():
            if k not in fields:
                raise ConfigError(f"method {spec.name!r} has no config field {k!r}; fields: "
                                  f"{', '.join(fields)}")
            merged[k] = _coerce(fields[k], hints[k], v, spec.name)
            layer_of[k] = i
    for field, needed in spec.requires.items():
        if layer_of.get(field) == 0 and layer_of.get(needed, 0) > 0 and not merged[needed]:
            del merged[field]
    try:
        return spec.config_cls(**merged)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"method {spec.name!r}: invalid config: {e}") from e
