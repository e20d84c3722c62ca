"""redmax_bench accuracy's stability maps fan out through the sweep runner: the same cells in this process
(workers=0) and on 2 local workers (wall times aside), and the maps' physics holds on them (the implicit
step stable at the largest h of the grid, semi-implicit Euler only below its explicit limit)."""
from redmax_bench import accuracy as A

SWEEP = {"spring": {"scene": "mass_springs", "overrides": ["params.n=1"], "param": "params.k", "values": [1e4, 1e6],
                    "unit": "N/m", "what": "one box on a spring"}}
METHODS = ["ours (direct)", "semi-implicit Euler (Pinocchio)"]


def _cells(res):
    out = []
    for mname, m in res["spring"]["methods"].items():
        for row in m["rows"]:
            out.append((mname, row["value"], row["h_max"], [(t["h"], t["status"], t["reason"]) for t in row["tried"]]))
    return out


def test_stability_cells_identical_inline_and_on_two_workers():
    inline = A.stability(SWEEP, METHODS, T=0.2, log=lambda *a: None, workers=0)
    pooled = A.stability(SWEEP, METHODS, T=0.2, log=lambda *a: None, workers=2)
    assert _cells(inline) == _cells(pooled)
    h = {(m, v): hm for m, v, hm, _ in _cells(pooled)}
    assert h[("ours (direct)", 1e4)] == h[("ours (direct)", 1e6)] == A.H_GRID[0]
    # explicit: stable only below ~2/omega, omega = sqrt(k/m) (m = 1 box), so a stiffer spring needs a smaller h
    assert h[("semi-implicit Euler (Pinocchio)", 1e6)] < h[("semi-implicit Euler (Pinocchio)", 1e4)] < A.H_GRID[0]
