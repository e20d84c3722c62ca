"""Scene files -> validated :class:`~redmax_ros.core.scene.spec.SceneSpec` (pure data, SI units;
docs/scenes.md): loader.py (YAML, ``key=value`` overrides, validation naming the entry of every problem),
spec.py (the dataclasses), registry.py and builders*.py (parametric scenes: chain, mass_springs, hand,
bridge, umbrella, friction scenes), bodies.py (composite and mesh bodies), files.py (where scene files may
come from, size caps, YAML alias and nesting limits), catalogue_schema.py and
contact_schema.py (the catalogue's and the contact/friction keys), timefunctions.py (time functions of
prescriptions and loads)."""
