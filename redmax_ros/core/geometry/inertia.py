"""Mass properties of primitive shapes (SI: kg, m, kg m^2), about the centre of mass, body frame.

Shapes are centred on the body frame origin; cylinders and capsules run along the body z axis.
"""
from __future__ import annotations

import math

import numpy as np


def shape_volume(shape: dict) -> float:
    """Volume [m^3] of a primitive shape dict (type box/cylinder/sphere/capsule)."""
    t = shape["type"]
    if t == "box":
        x, y, z = shape["size"]
        return x * y * z
    if t == "sphere":
        return 4.0 / 3.0 * math.pi * shape["radius"] ** 3
    if t == "cylinder":
        return math.pi * shape["radius"] ** 2 * shape["length"]
    if t == "capsule":
        r, L = shape["radius"], shape["length"]
        return math.pi * r * r * L + 4.0 / 3.0 * math.pi * r ** 3
    raise ValueError(f"unknown shape type '{t}'")


def shape_inertia(shape: dict, mass: float) -> np.ndarray:
    """3x3 rotational inertia [kg m^2] about the COM of a uniform solid of the given mass."""
    t = shape["type"]
    if t == "box":
        x, y, z = shape["size"]
        return mass / 12.0 * np.diag([y * y + z * z, x * x + z * z, x * x + y * y])
    if t == "sphere":
        return 0.4 * mass * shape["radius"] ** 2 * np.eye(3)
    if t == "cylinder":
        r, L = shape["radius"], shape["length"]
        ixx = mass * (3 * r * r + L * L) / 12.0
        return np.diag([ixx, ixx, 0.5 * mass * r * r])
    if t == "capsule":
        # Cylinder of length L plus two hemispheres (standard closed form).
        r, L = shape["radius"], shape["length"]
        fc = L / (L + 4.0 / 3.0 * r)  # cylinder's share of the volume, pi r^2 L / (pi r^2 L + 4/3 pi r^3)
        mc, ms = mass * fc, mass * (1.0 - fc)
        izz = 0.5 * mc * r * r + 0.4 * ms * r * r
        ixx = mc * (3 * r * r + L * L) / 12.0 + ms * (0.4 * r * r + L * L / 4.0 + 3.0 * L * r / 8.0)
        return np.diag([ixx, ixx, izz])
    raise ValueError(f"unknown shape type '{t}'")
