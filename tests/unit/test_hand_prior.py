"""The hand-pose prior table (thesis 7.22) trajopt reads: shipped, current with the scripted teacher
it is written from, refused with a hint when missing or incomplete; trajopt never imports the world."""

from __future__ import annotations

import json

import pytest

from learning.hand_prior import teacher_table
from services.trajopt.hand_prior import DEFAULT_PRIOR, load_prior
from shared.robots.registry import describe
from tests.unit.test_policy_layering import ROOT, imports


def test_the_shipped_table_is_the_scripted_teachers_current_prior():
    shipped, fresh = json.loads(DEFAULT_PRIOR.read_text()), teacher_table()
    assert shipped["source"] == fresh["source"] and shipped["frames"] == fresh["frames"]
    for hand in ("left", "right"):
        for stat in ("mean", "std"):
            # 1e-6 rad: float32 sums in the simulation differ by ~6e-8 between CPUs (AMD / Intel)
            assert shipped[hand][stat] == pytest.approx(fresh[hand][stat], abs=1e-6), \
                f"{hand} {stat}: run `python -m learning.hand_prior`"


def test_load_prior_reads_the_robots_joints_and_refuses_a_missing_or_incomplete_table(tmp_path):
    chains = describe("hand_arm").finger_flexion
    mean, std = load_prior(chains, "right")
    assert set(mean) == set(std) == set(chains) and min(std.values()) > 0
    with pytest.raises(ValueError, match="no hand-pose prior at .*python -m learning.hand_prior"):
        load_prior(chains, "right", tmp_path / "none.json")
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"right": {"mean": {}, "std": {}}}))
    with pytest.raises(ValueError, match="lacks .* for the right hand"):
        load_prior(chains, "right", partial)


@pytest.mark.parametrize("path", sorted((ROOT / "services" / "trajopt").glob("*.py")), ids=lambda p: p.name)
def test_trajopt_does_not_import_the_simulated_world(path):
    top, nested = imports(path)
    assert not [n for n in top | {n for _, n in nested} if n.startswith("services.world")]
