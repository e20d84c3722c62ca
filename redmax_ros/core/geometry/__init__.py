"""Geometry and the joint catalogue's mathematics (bottom layer; no scene, no model): joint maps Q, S, Sdot
of every joint of Sueda's notes §2.5 (joints.py), spline joints (Alg. 3-4, spline_joints.py), Euler-angle
charts and their switching (Eq. 2.38-2.40, euler_charts.py), mass properties of shapes (inertia.py) and of
closed triangle meshes by Mirtich's volume integrals (mesh.py)."""
