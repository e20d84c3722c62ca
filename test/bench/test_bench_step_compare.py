"""redmax_bench step runs every engine column on a scene MuJoCo can take and says why a column is n/a
where it cannot (prescribed motion, contact and joint friction, the compiled backend until it lands).
Structure only: a few steps, no timing assertions."""
import json

import pytest

from redmax_bench import mujoco_export, step

pytestmark = pytest.mark.skipif(not mujoco_export.available(), reason="mujoco is not installed (pip install -e .[bench])")


def test_step_columns_targets_and_reasons(tmp_path):
    assert step.main(["--steps", "3", "--repeats", "1", "--no-chart", "--out", str(tmp_path),
                      "--scenes", "fourbar,klann"]) == 0
    out = json.loads((tmp_path / "step.json").read_text())
    assert out["columns"] == step.COLUMNS and out["versions"]["mujoco"] and out["versions"]["pinocchio"]
    rows = {r["case"]: r for r in out["rows"]}
    assert set(rows) == {"fourbar", "klann walker"}
    for r in rows.values():
        us, na = r["us_per_step"], r["na"]
        assert us[step.REF] > 0 and us[step.SIE] > 0
        assert (us[step.COMPILED] is None) == (step.COMPILED in na)  # a figure, or n/a with its reason
        assert r["target"]["status"] in ("met", "missed", "n/a")
        assert r["target"]["ours"] == (step.REF if us[step.COMPILED] is None else step.COMPILED)
    fb, walker = rows["fourbar"], rows["klann walker"]
    assert all(fb["us_per_step"][c] > 0 for c in step.MJ.values())
    assert fb["ratios"]["reference/MJ implicitfast"] == pytest.approx(
        fb["us_per_step"][step.REF] / fb["us_per_step"][step.MJ["implicitfast"]])
    for c in step.MJ.values():
        assert walker["us_per_step"][c] is None and "friction" in walker["na"][c]
    assert any("friction" in n for n in out["notes"])


def test_unknown_scene_is_refused():
    with pytest.raises(SystemExit, match="unknown scene"):
        step.select(["no_such_scene"])
    assert [c.label for c in step.select(["hand"])] == ["hand", "hand 5 tips+elbow"]
