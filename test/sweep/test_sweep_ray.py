"""The same sweep on Ray (a local Ray started here with 2 CPUs) gives the rows of the local pool, and a task
whose worker dies is retried once there too (redmax_ros/sweep/pool.py, ``pip install .[cluster]``)."""
import pytest
import ray

from redmax_ros.sweep.cli import sweep
from test_sweep_pool import _comparable, _runs


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_ray_rows_equal_local_rows_and_dead_workers_are_retried(tmp_path, local_ray):
    keys, runs = _runs(tmp_path, "kill_at_q0")
    ray_rows, _ = sweep(runs, keys, tmp_path / "ray", ray_address="auto", progress=False)
    (tmp_path / "killed_once").unlink()
    local_rows, _ = sweep(runs, keys, tmp_path / "local", workers=2, progress=False)
    a, _ = _comparable(tmp_path / "ray" / "runs.csv")
    b, _ = _comparable(tmp_path / "local" / "runs.csv")
    assert a == b  # bitwise, failures included
    by = {r["joints.hinge.q0"]: r for r in ray_rows}
    assert by["0.2"]["status"] == "killed" and by["0.2"]["attempts"] == 2
    assert by["0.3"]["status"] == "ok" and by["0.3"]["attempts"] == 2
    assert [r["attempts"] for r in ray_rows] == [r["attempts"] for r in local_rows]
    assert ray.is_initialized()  # a Ray the caller started is left running
