"""No truth outside evaluation: in the deployments that ship, no service but the world (which
publishes it) and the recorder (which records what a start command names) reads
`xm/world/sim/truth`. recon's simulated detector is the one labelled exception, and only where a
deployment chooses it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from shared.config import load_deployment
from shared.wiring import bind, edges, intersects

ROOT = Path(__file__).resolve().parents[2]
DEPLOYMENTS = sorted((ROOT / "deploy").glob("*.toml"))
TRUTH = "xm/world/sim/truth"


def truth_readers(path: Path) -> set[str]:
    """Instances whose bound inputs subscribe to a key expression that meets the truth key."""
    dep = load_deployment(path)
    readers = set()
    for service, instance in dep.instances():
        for inp in bind(dep, service, instance).inputs.values():
            if any(intersects(expr, TRUTH) for expr in inp.key_exprs):
                readers.add(f"{service}/{instance}")
    return readers


@pytest.mark.parametrize("path", DEPLOYMENTS, ids=lambda p: p.name)
def test_no_shipped_deployment_reads_the_truth(path):
    assert truth_readers(path) == set(), f"{path.name} subscribes to {TRUTH}"
    wired, _ = edges(load_deployment(path))
    assert not [e for e in wired if e.output == "truth"], path.name


def test_recon_reads_the_truth_only_when_the_simulated_detector_is_chosen(tmp_path):
    text = (ROOT / "deploy" / "sim.toml").read_text()
    assert re.search(r'^detector = "learned"', text, re.M), "make run must use the learned detector"
    chosen = tmp_path / "experiment.toml"
    chosen.write_text(re.sub(r'^detector = "learned"', 'detector = "simulated"', text, flags=re.M))
    assert truth_readers(chosen) == {"recon/main"}
    wired, problems = edges(load_deployment(chosen))
    assert {(e.producer, e.consumer, e.input) for e in wired if e.output == "truth"} == \
        {("world/sim", "recon/main", "truth")}
    assert problems == []


def test_no_service_node_names_the_truth_in_its_code():
    """Beyond the declared ports: no service's node code subscribes to the truth key by name.
    The world publishes it; recon's service holds the simulated detector's (declared, optional)
    path; command-line tools (cli.py: offline evaluation) may read recordings' truth."""
    allowed = {"services/world", "services/recorder", "services/recon/service.py", "services/recon/ports.py"}
    offenders = []
    for py in sorted((ROOT / "services").rglob("*.py")):
        rel = py.relative_to(ROOT).as_posix()
        if py.name == "cli.py" or any(rel == a or rel.startswith(a + "/") for a in allowed):
            continue
        if re.search(r"world/[\w*]+/truth|GroundTruth|input\(\s*[\"']truth", py.read_text()):
            offenders.append(rel)
    assert offenders == []
