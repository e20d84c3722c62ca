"""Parametric scenes: the registry of builders (``builder: chain`` in a scene file) and the
helpers builders use to read their parameters."""
from __future__ import annotations

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


def int_param(p, key, lo=0):
    """``p[key]`` as an integer >= lo (ValueError otherwise)."""
    v = p[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"'{key}' must be an integer >= {lo}, got {v!r}")
    return v
