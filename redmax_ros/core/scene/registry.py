"""Parametric scenes: the registry of builders (``builder: chain`` in a scene file) and the
helpers builders use to read their parameters."""
from __future__ import annotations

from redmax_ros.core.scene.files import MAX_BODIES

BUILDERS: dict = {}


def register_builder(name: str):
    """Decorator: register ``fn(params: dict) -> scene dict`` under ``name`` for ``builder: name``."""

    def deco(fn):
        BUILDERS[name] = fn
        return fn

    return deco


def take(params: dict, defaults: dict) -> dict:
    """``defaults`` updated with ``params``; ValueError naming unknown parameters."""
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown} (known: {sorted(defaults)})")
    out = dict(defaults)
    out.update(params)
    return out


def int_param(p, key, lo=0, hi=MAX_BODIES):
    """``p[key]`` as an integer in [lo, hi] (ValueError otherwise; ``hi``: a count larger than a scene may be
    is refused before anything is built)."""
    v = p[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"'{key}' must be an integer >= {lo}, got {v!r}")
    if v > hi:
        raise ValueError(f"'{key}' = {v} is above the limit of {hi}")
    return v


def bool_param(p, key) -> bool:
    """``p[key]`` as a bool (true/false in the scene file), ValueError for anything else (a string such as
    'maybe' would otherwise read as true)."""
    v = p[key]
    if not isinstance(v, bool):
        raise ValueError(f"'{key}' must be true or false, got {v!r}")
    return v
