"""Typed, range-checked configs of the training commands: one table ``key -> Spec`` per command,
generated from its schema dataclass (:mod:`training.schema`, :func:`specs_of`).

Hydra's struct mode already rejects unknown keys, but not values: ``steps=abc`` used to fail deep in
``int()`` without the key, ``steps=1.5`` silently ran one step, ``resume=no`` resumed (a non-empty
string is truthy) and ``sh.n_smooth_iters=-3`` or ``edge_length=nan`` passed. :func:`check_config`
checks every key of a composed config against its :class:`Spec` once, before anything runs, and
raises :class:`ConfigError` naming the key, the value, what is allowed and the config file.

Rules (the same for every command):

- a value is never coerced: ``1.5`` is not an ``int``, ``"no"`` is not a ``bool``, ``1`` is not a
  ``bool``; an ``int`` is accepted where a ``float`` is expected (``lr=1``);
- floats must be finite unless a range says otherwise;
- ``null`` only where the spec says so (``nullable``).

:class:`ConfigError` subclasses :class:`ValueError` (callers that caught ``ValueError`` keep
working) and lives here, in ``training/``, not in :mod:`torchconn`: the library takes typed Python
arguments and checks them itself; keys, overrides and config files are the commands' concepts.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from . import schema

__all__ = ["DEMO", "HEX_MESH", "TRAIN_FRAMES", "ConfigError", "Spec", "check_config", "check_device", "resolve_num_threads",
           "specs_of"]


class ConfigError(ValueError):
    """A config value of the wrong type or out of range (the message names key, value, allowed, file)."""


@dataclass(frozen=True)
class Spec:
    """What one config key accepts.

    Attributes:
        kind: ``"bool" | "int" | "float" | "str" | "choice" | "device" | "threads" | "list"``.
        lo, hi: inclusive bounds for ``int``/``float`` (``None``: unbounded).
        lo_open: ``lo`` itself is excluded (``lr > 0``).
        choices: allowed values of a ``choice``.
        nullable: ``null`` is allowed.
        item: the spec of every element of a ``list`` (a non-empty list; ``lo``/``hi`` unused).
    """

    kind: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple = ()
    nullable: bool = False
    item: "Spec | None" = None

    def describe(self) -> str:
        """What is allowed, in words (used in the error message)."""
        if self.kind == "bool":
            s = "a boolean: true or false"
        elif self.kind in ("int", "float"):
            s = "an integer" if self.kind == "int" else "a finite number"
            if self.lo is not None:
                s += f" {'>' if self.lo_open else '>='} {self.lo:g}"
            if self.hi is not None:
                s += f"{' and' if self.lo is not None else ''} <= {self.hi:g}"
        elif self.kind == "choice":
            s = f"one of {list(self.choices)}"
        elif self.kind == "device":
            s = "an available torch device: 'cpu', or 'cuda'/'cuda:N' where CUDA is available"
        elif self.kind == "threads":
            s = "'auto' or an integer >= 1"
        elif self.kind == "list":
            s = f"a non-empty list, each element {self.item.describe()}"
        else:
            s = "a non-empty string"
        return s + (" or null" if self.nullable else "")


def _spec_of_type(tp, meta: Mapping, where: str) -> Spec:
    """The :class:`Spec` of one field of type ``tp`` (``X | None`` nullable) and ``metadata`` ``meta``."""
    args = typing.get_args(tp)
    nullable = type(None) in args
    if nullable:
        rest = tuple(a for a in args if a is not type(None))
        tp = rest[0] if len(rest) == 1 else typing.Union[rest]
    kind = meta.get("kind")
    if kind is not None:
        return Spec(kind, nullable=nullable)
    if typing.get_origin(tp) is list:
        (item,) = typing.get_args(tp)
        return Spec("list", item=_spec_of_type(item, meta, where), nullable=nullable)
    bounds = {"lo": meta.get("lo"), "hi": meta.get("hi"), "lo_open": bool(meta.get("lo_open", False))}
    if tp is bool:
        return Spec("bool", nullable=nullable)
    if tp is int:
        return Spec("int", nullable=nullable, **bounds)
    if tp is float:
        return Spec("float", nullable=nullable, **bounds)
    if tp is str:
        if "choices" in meta:
            return Spec("choice", choices=tuple(meta["choices"]), nullable=nullable)
        return Spec("str", nullable=nullable)
    raise TypeError(f"schema field {where}: no check for type {tp!r} (give it metadata kind=...)")


def specs_of(schema, prefix: str = "") -> dict[str, Spec]:
    """``{"dotted.key": Spec}`` of a schema dataclass (:mod:`training.schema`), nested groups
    flattened: the field's type says the kind and whether ``null`` is allowed, its ``metadata``
    (:func:`torchconn.frames.options.option`) the range, the choices or a special ``kind``."""
    hints = typing.get_type_hints(schema)
    out: dict[str, Spec] = {}
    for f in dataclasses.fields(schema):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out.update(specs_of(tp, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = _spec_of_type(tp, f.metadata, f"{schema.__name__}.{f.name}")
    return out


#: The keys of the frame job (:class:`training.schema.TrainFramesConfig`).
TRAIN_FRAMES: dict[str, Spec] = specs_of(schema.TrainFramesConfig)
#: The keys of the hex job (:class:`training.schema.HexMeshConfig`).
HEX_MESH: dict[str, Spec] = specs_of(schema.HexMeshConfig)
#: The keys of the demo (:class:`training.schema.DemoConfig`).
DEMO: dict[str, Spec] = specs_of(schema.DemoConfig)


def _flatten(cfg: Mapping, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in cfg.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _type_name(v) -> str:
    return "null" if v is None else type(v).__name__


def check_device(value, key: str = "device", source: str = "the config") -> torch.device:
    """``torch.device(value)`` if that device exists here, else :class:`ConfigError` naming ``key``."""
    try:
        dev = torch.device(value)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise ConfigError(f"config key {key!r} in {source}: {value!r} is not a torch device ({exc}); use e.g. "
                          f"{key}=cpu") from exc
    if dev.type == "cpu":
        return dev
    backend = getattr(torch, dev.type, None) if dev.type != "mps" else torch.backends.mps
    available = bool(backend is not None and hasattr(backend, "is_available") and backend.is_available())
    if not available:
        raise ConfigError(f"config key {key!r} in {source}: device {value!r} is not available in this torch build/machine "
                          f"(torch {torch.__version__}); use {key}=cpu")
    count = getattr(backend, "device_count", lambda: 1)()
    if dev.index is not None and dev.index >= count:
        raise ConfigError(f"config key {key!r} in {source}: device {value!r} does not exist ({count} {dev.type} device(s)); "
                          f"use an index < {count}")
    return dev


def _check_value(key: str, v, spec: Spec, source: str) -> str | None:
    """``None`` if ``v`` satisfies ``spec``, else the reason."""
    if v is None:
        return None if spec.nullable else "null is not allowed"
    kind = spec.kind
    if kind == "list":
        if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or not hasattr(v, "__iter__"):
            return "not a list"
        if len(v) == 0:
            return "an empty list"
        for i, x in enumerate(v):
            why = _check_value(f"{key}[{i}]", x, spec.item, source)
            if why is not None:
                return f"element {i} ({x!r}) is {why}"
        return None
    if kind == "bool":
        return None if isinstance(v, bool) else "not a boolean"
    if kind == "threads":
        if v == "auto":
            return None
        kind = "int"
        spec = Spec("int", lo=1)
    if kind == "int":
        if not _is_int(v):
            return "not an integer" + (" (a fraction is never rounded)" if isinstance(v, float) else "")
    elif kind == "float":
        if not (_is_int(v) or isinstance(v, float)):
            return "not a number"
        if not math.isfinite(float(v)):
            return "not finite"
    elif kind == "choice":
        return None if v in spec.choices and type(v) is type(spec.choices[0]) else "not an allowed choice"
    elif kind in ("str", "device"):
        if not isinstance(v, (str, os.PathLike)) or not str(v).strip():
            return "not a non-empty string"
        if kind == "device":
            check_device(str(v), key, source)
        return None
    x = float(v)
    if spec.lo is not None and (x < spec.lo or (spec.lo_open and x == spec.lo)):
        return "out of range"
    if spec.hi is not None and x > spec.hi:
        return "out of range"
    return None


def check_config(cfg, schema: Mapping[str, Spec], source: str) -> None:
    """Check every key of ``cfg`` against ``schema``.

    Args:
        cfg: a ``DictConfig`` or nested dict (keys missing from ``cfg`` are not checked: the
            caller merges the defaults first).
        schema: ``{"dotted.key": Spec}``, e.g. :data:`TRAIN_FRAMES` (:func:`specs_of` a schema dataclass).
        source: the config file, named in messages (e.g. ``"configs/train_frames.yaml"``).

    Raises:
        ConfigError: for the first bad key, e.g. ``config key 'steps' = 1.5 (float) in
            configs/train_frames.yaml is not an integer (a fraction is never rounded); allowed:
            an integer >= 0. Fix it in the file or override it: steps=...``; also for a key not
            in ``schema`` and a value whose interpolation cannot be resolved.
    """
    if isinstance(cfg, DictConfig):
        raw = _flatten(OmegaConf.to_container(cfg, resolve=False))
        values = {}
        for key in raw:
            try:
                values[key] = OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
            except Exception as exc:
                raise ConfigError(f"config key {key!r} = {raw[key]!r} in {source} cannot be resolved here "
                                  f"({type(exc).__name__}: {str(exc).splitlines()[0]}); set it explicitly "
                                  f"({key}=...)") from exc
    else:
        values = _flatten(cfg)
    for key, v in values.items():
        if key not in schema:
            close = difflib.get_close_matches(key, list(schema), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(f"config key {key!r} is not a key of {source}; {hint}allowed keys: {sorted(schema)}")
        reason = _check_value(key, v, schema[key], source)
        if reason is not None:
            raise ConfigError(f"config key {key!r} = {v!r} ({_type_name(v)}) in {source} is {reason}; allowed: "
                              f"{schema[key].describe()}. Fix it in the file or override it: {key}=...")


def resolve_num_threads(value) -> int | None:
    """The intra-op thread count for ``num_threads`` (``None``: leave torch's setting alone).

    ``"auto"``: the cores this process may run on (``os.sched_getaffinity``) minus the busy ones
    (the 1-minute load average, rounded), at least 1 and at most torch's default. A loaded machine
    thus gets fewer threads: threads that wait for a descheduled sibling made the default job 5 to
    11 times slower with 2 threads than with 1 on a loaded 2-core machine (measurements: the
    ``num_threads`` measurements below).

    Seconds of the default frame job on a 2-core machine shared with other jobs (metrics.json
    ``timings.wall_s``; ``python -m training.train_frames num_threads=N``): load ~4.5: cylinder 1 thread
    8.2, 2 threads 40.3, auto (-> 1) 4.5; sphere_r0.17.mesh 1 thread 4.7, 2 threads 13.5, auto (-> 1) 2.9;
    load ~8 (+ a busy loop): cylinder 1 thread 26.4, 2 threads 287.5; load ~1.5 (no busy loop):
    cylinder 1 thread 6.0, 2 threads 5.9 (whole process, imports included).
    """
    if value is None:
        return None
    if value != "auto":
        return int(value)
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    try:
        busy = round(os.getloadavg()[0])
    except (AttributeError, OSError):  # Windows
        busy = 0
    return max(1, min(cpus - busy, torch.get_num_threads()))
