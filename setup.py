"""ament_python build script for redmax_ros.

Used both by colcon (apt ROS install, see README "Using an apt ROS install") and
by ``pip install -e .[test,bench,cluster]`` in the PyPI-wheel venv made by scripts/setup.sh.
In both cases the data files below land in ``<prefix>/share/redmax_ros`` and the
ament index marker in ``<prefix>/share/ament_index/resource_index/packages``, so
``ament_index_python.get_package_share_directory('redmax_ros')`` works.
"""
import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "redmax_ros"
HERE = os.path.dirname(os.path.abspath(__file__))


def tree(folder, patterns):
    """data_files entries for every file under ``folder`` matching ``patterns``,
    keeping subfolders: scenes/hand/x.yaml -> share/redmax_ros/scenes/hand/x.yaml."""
    found = {}
    for pattern in patterns:
        for path in glob(os.path.join(folder, "**", pattern), recursive=True):
            if os.path.isfile(os.path.join(HERE, path)):
                found.setdefault(os.path.dirname(path), []).append(path)
    return [
        (os.path.join("share", PACKAGE, sub), sorted(files))
        for sub, files in sorted(found.items())
    ]


# Relative paths are required by setuptools for data_files; run from the project root.
os.chdir(HERE)

data_files = [
    ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
    (f"share/{PACKAGE}", ["package.xml"]),
]
data_files += tree("config", ["*.yaml"])
data_files += tree("scenes", ["*.yaml", "*.urdf", "*.xml"])
data_files += tree("launch", ["*.launch.py", "*.launch.xml", "*.launch.yaml"])

setup(
    name=PACKAGE,
    version="0.1.0",
    description="RedMax articulated-body simulator core with a ROS 2 Jazzy node",
    license="MIT",
    maintainer="RedMax ROS maintainers",
    maintainer_email="maintainers@redmax-ros.dev",
    python_requires=">=3.10",
    # redmax_bench: the benchmarks, a separate top-level package beside the runtime (it imports
    # redmax_ros.core's public API; results go to its --out directory, never into the install).
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*", "redmax_bench", "redmax_bench.*"]),
    data_files=data_files,
    zip_safe=False,
    # ROS Python packages (rclpy, *_msgs, redmax_msgs) are deliberately absent:
    # they come from package.xml (apt/rosdep) or from the ros-jazzy-* wheels that
    # scripts/setup.sh installs. Keep this list in sync with package.xml's comment.
    install_requires=[
        "numpy",
        "pin>=4.1,<5",
        "numba",  # JIT kernels of the O(n) passes and the matrix-free PCG solver (core/recursive.py, docs/solvers.md)
        "proxsuite",
        "pyyaml",
        "mcap",
        "mcap-ros2-support",
        "tqdm",  # progress bars of redmax_run, redmax_sweep and redmax_bench
        "pyarrow",  # redmax_sweep's Parquet results table (redmax_ros/sweep/table.py)
        "scipy",  # sparse LU of the coupled deformable solve (sparse matrices of the deformables)
        "meshio",  # tetrahedral mesh files of deformables (.msh, .vtk, .vtu; core/deformable/mesh_io.py)
    ],
    extras_require={
        # Benchmarks (redmax_bench): MuJoCo and Exudyn as comparators, matplotlib for the charts.
        "bench": ["mujoco", "matplotlib", "exudyn>=1.9"],
        "test": ["pytest", "pytest-xdist", "rosbags", "mcap", "mcap-ros2-support"],
        # redmax_sweep --ray and redmax_bench --ray: sweeps on a Ray cluster (docs/sweeps.md)
        "cluster": ["ray[default]>=2.40,<3"],
    },
    entry_points={
        "console_scripts": [
            "redmax_run = redmax_ros.runner:main",
            "redmax_node = redmax_ros.node.main:cli",
            "redmax_bench = redmax_bench.cli:main",
            "redmax_sweep = redmax_ros.sweep.cli:main",
        ],
    },
)
