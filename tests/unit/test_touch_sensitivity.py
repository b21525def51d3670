"""evaluation/touch_sensitivity.py: the force-decided success tests under a height error, force
from the positions (no touch) against force from the glove (force control)."""

from __future__ import annotations

import pytest

from evaluation.touch_sensitivity import main, sensitivity, table
from services.world.tasks import UnknownTaskError
from services.world.teacher import generate_demo


def _rates(result: dict, source: str) -> dict[float, float]:
    return {r["offset_mm"]: r[source]["success_rate"] for r in result["rows"]}


def test_wiping_from_positions_tolerates_a_millimetre_and_the_glove_several():
    d = generate_demo("wiping", 2, grasp_hand="right", tactile_hand="right")
    result = sensitivity("wiping", [d], (0.0, 3.0, 10.0))
    assert _rates(result, "positions") == {0.0: 1.0, 3.0: 0.0, 10.0: 0.0}  # 3 mm up: the foam is not pressed
    # force control closes 5 mm: the pad, pressed 3-4 mm deep, is then 6-7 mm above the plate
    assert _rates(result, "glove") == {0.0: 1.0, 3.0: 1.0, 10.0: 0.0}
    assert "| +3.0 | 0 %" in table(result)


def test_latch_from_the_glove_needs_the_tip_within_reach():
    d = generate_demo("latch", 3, grasp_hand="right", tactile_hand="left")  # glove on the pressing hand
    result = sensitivity("latch", [d], (0.0, 3.0, 10.0))
    assert _rates(result, "glove") == {0.0: 1.0, 3.0: 1.0, 10.0: 0.0}
    assert _rates(result, "positions")[3.0] == 0.0  # 3 mm above: a position-controlled finger never touches


def test_a_task_without_a_force_measure_is_refused(capsys):
    with pytest.raises(UnknownTaskError, match="no force-decided measure"):
        sensitivity("pick_place", [])
    assert main(["--task", "assembly"]) == 2
    assert "unknown task 'assembly'" in capsys.readouterr().out
