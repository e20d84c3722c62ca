"""Shared set-up of the whole suite: the environment, the ROS 2 domain, scene loading.

The test folders mirror the packages (test/core/<sub-package>/, test/node/, test/logging/,
test/bench/; test_layers.py and test_runner.py are about redmax_ros as a whole and redmax_ros/runner.py).
The folders have no __init__.py: pytest's default ("prepend") import mode puts each test file's folder
on sys.path and imports the file under its basename, so basenames are unique across the suite and a
helper module next to its tests (node/node_fixtures.py, core/solvers/recursive_models.py) imports
by name.

Environment (``pytest_configure``, before any test module is imported):

* BLAS single-threaded (OPENBLAS/OMP/MKL_NUM_THREADS=1 unless set), as redmax_ros/__init__.py
  arranges for the package; here it holds whichever module imports numpy first.
* A private ROS 2 graph, as scripts/test.sh sets it: ROS_DOMAIN_ID (derived from the process id
  unless set), ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and RMW_IMPLEMENTATION=rmw_fastrtps_cpp
  unless set. A node started by a test as a subprocess inherits them.
* Under pytest-xdist (scripts/test.sh runs ``-n 2 --dist loadfile``), each worker gets a graph of its
  own: worker ``gwN`` moves the run's domain by N * DOMAIN_STRIDE (wrapping in 1..232), so two workers'
  nodes, services and topics never see each other.

Fixtures: ``ros_domain`` (session: the domain id, checked private), ``ros`` (module: rclpy.init and
rclpy.shutdown around a test module's ROS tests), ``load_sim`` (Simulator.load as a factory) and ``rk4_aba``
(the RK4 reference of the order tests).
"""
from __future__ import annotations

import os

import pytest

BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
ROS_DISCOVERY = "LOCALHOST"
ROS_DOMAIN_MAX = 232  # the largest domain id Fast DDS maps to valid ports on Linux
DOMAIN_STRIDE = 101  # domain offset between pytest-xdist workers (scripts/test.sh draws the base from 1..101)


def worker_domain(base: int, worker: str) -> int:
    """The ROS_DOMAIN_ID of pytest-xdist worker ``worker`` ("gw0", "gw1", ...) in a run whose domain is
    ``base``: base + N * DOMAIN_STRIDE, wrapped into 1..ROS_DOMAIN_MAX (gw0 keeps the base)."""
    n = int(worker.removeprefix("gw"))
    return (base - 1 + n * DOMAIN_STRIDE) % ROS_DOMAIN_MAX + 1


def pytest_configure(config):
    for var in BLAS_THREADS:
        os.environ.setdefault(var, "1")
    os.environ.setdefault("ROS_DOMAIN_ID", str(20 + os.getpid() % 80))
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker and os.environ["ROS_DOMAIN_ID"].isdigit():
        os.environ["ROS_DOMAIN_ID"] = str(worker_domain(int(os.environ["ROS_DOMAIN_ID"]), worker))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", ROS_DISCOVERY)
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


def pytest_report_header(config):
    env = os.environ
    return (f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']} ROS_AUTOMATIC_DISCOVERY_RANGE={env['ROS_AUTOMATIC_DISCOVERY_RANGE']} "
            f"RMW_IMPLEMENTATION={env['RMW_IMPLEMENTATION']} OPENBLAS_NUM_THREADS={env['OPENBLAS_NUM_THREADS']}")


@pytest.fixture(scope="session")
def ros_domain() -> int:
    """The ROS_DOMAIN_ID of this run; fails, saying why, unless the graph is private (a domain other
    than the default 0, discovery limited to this machine)."""
    raw = os.environ.get("ROS_DOMAIN_ID", "")
    discovery = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "")
    try:
        domain = int(raw)
    except ValueError:
        domain = -1
    if not 1 <= domain <= ROS_DOMAIN_MAX:
        pytest.fail(f"ROS_DOMAIN_ID={raw!r}: the ROS tests need a private domain, an integer in 1..{ROS_DOMAIN_MAX} "
                    "(0 is the default every ROS 2 process joins); unset ROS_DOMAIN_ID (scripts/test.sh and this "
                    "conftest then pick one) or set it in that range", pytrace=False)
    if discovery != ROS_DISCOVERY:
        pytest.fail(f"ROS_AUTOMATIC_DISCOVERY_RANGE={discovery!r}: the ROS tests need {ROS_DISCOVERY} (no traffic "
                    "to other machines); unset the variable or run scripts/test.sh, which sets it", pytrace=False)
    return domain


@pytest.fixture(scope="module")
def ros(ros_domain):
    """rclpy initialised for the test module (its nodes and clients), shut down after its last test
    (unless a signal, e.g. Ctrl-C, has shut it down already)."""
    if os.environ.get("CI"):  # in CI a missing ROS environment is a failure, not a skip
        import rclpy
    else:
        rclpy = pytest.importorskip("rclpy")
    rclpy.init()
    yield rclpy
    rclpy.try_shutdown()


@pytest.fixture
def load_sim():
    """``load_sim(name_or_path, overrides=(), solver=None)``: ``Simulator.load`` of the core, a fresh
    Simulator per call."""
    from redmax_ros.core import Simulator

    def load(name_or_path, overrides=(), solver=None):
        return Simulator.load(name_or_path, overrides, solver=solver)
    return load


@pytest.fixture
def rk4_aba():
    """``rk4_aba(model, q, v, T, h=1e-4)``: the configuration after T s of classical RK4 on Pinocchio's ABA
    (tree, no applied torques), q updated on the manifold: the reference of the order tests."""
    import numpy as np
    import pinocchio as pin

    def run(model, q, v, T, h=1e-4):
        d = model.createData()
        q, v, tau = np.array(q, float), np.array(v, float), np.zeros(model.nv)
        for _ in range(int(round(T / h))):
            k1v, k1a = v, pin.aba(model, d, q, v, tau)
            k2v = v + 0.5 * h * k1a
            k2a = pin.aba(model, d, pin.integrate(model, q, 0.5 * h * k1v), k2v, tau)
            k3v = v + 0.5 * h * k2a
            k3a = pin.aba(model, d, pin.integrate(model, q, 0.5 * h * k2v), k3v, tau)
            k4v = v + h * k3a
            k4a = pin.aba(model, d, pin.integrate(model, q, h * k3v), k4v, tau)
            q = pin.integrate(model, q, h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))
            v = v + h / 6 * (k1a + 2 * k2a + 2 * k3a + k4a)
        return q
    return run
