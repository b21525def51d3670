"""The glove's layout is its cell map file (shared/cellmap.py, services/glove/layout.py): a cell map
written by `xm skin` with another palm cutout changes what the glove service publishes and reports
and what the tactile projection samples; a missing, malformed or inconsistent one is refused,
naming the file and the problem, counted and reported in @health."""

from __future__ import annotations

import copy
import json
import logging
from types import SimpleNamespace

import numpy as np
import pytest

from services.glove import layout as glove_layout
from services.glove.layout import DEFAULT_CELLMAP, CellMapError
from services.glove.service import GloveService, cell_mask
from services.recon.hand_mesh import PALM as PALM_CHAIN
from services.recon.service import ReconService
from services.recon.tactile_projection import TactileProjector
from shared.demo import TACTILE_REGIONS
from shared.runtime.node import Stats
from skin import cli as skin_cli

PALM = TACTILE_REGIONS.index("palm")
MOVED = [[4, 0], [4, 1], [4, 2], [5, 0], [5, 1], [5, 2]]  # the cutout at the little finger's side
SHIPPED = [[4, 3], [4, 4], [4, 5], [5, 3], [5, 4], [5, 5]]  # between thumb and index


class FakeNode:
    """What GloveService and ReconService use of a Node."""

    def __init__(self, instance: str = "left") -> None:
        self.instance = instance
        self.clock = SimpleNamespace(now=lambda: 0.0, mode="wall")
        self.outputs: dict[str, list] = {}
        self.handlers: dict[str, object] = {}
        self.stats = Stats()
        self.log = logging.getLogger("test-cellmap")
        self.status, self.message = "starting", ""
        self.health_extra = None

    def output(self, port: str):
        return SimpleNamespace(put=self.outputs.setdefault(port, []).append)

    def input(self, port: str, handler) -> None:
        self.handlers[port] = handler

    def queryable(self, name: str, handler) -> None:
        self.handlers[name] = handler

    def set_status(self, status: str, message: str = "") -> None:
        self.status, self.message = status, message


def glove(node: FakeNode, cellmap: str = "") -> GloveService:
    return GloveService(node, GloveService.Params(port="/nonexistent/glove", cellmap=cellmap,
                                                  tty_worker_rt_priority=0))


@pytest.fixture(scope="module")
def moved_cutout(tmp_path_factory) -> str:
    """The glove's cell map with the palm's cutout at the little finger's side, written by xm skin."""
    out = tmp_path_factory.mktemp("skin")
    assert skin_cli.main(["glove", "--cellmap-only", "--palm-cutout", "4", "0", "2", "3", "--out", str(out)]) == 0
    return str(out / "glove_cellmap.json")


def test_the_shipped_cell_map_is_the_default_layout():
    lay = glove_layout.default()
    assert lay.path == str(DEFAULT_CELLMAP) and DEFAULT_CELLMAP.is_file()
    assert lay.cutouts() == {"palm": SHIPPED}
    np.testing.assert_array_equal(glove_layout.CELL_REGION, lay.region)
    assert (glove_layout.TX_MASK, glove_layout.RX_MASK) == (0xFFFF, 0x3F)


def test_another_cutout_changes_what_the_glove_service_reports_and_publishes(moved_cutout):
    shipped, moved = FakeNode(), FakeNode()
    glove(shipped)
    service = glove(moved, moved_cutout)
    assert moved.status == "starting" and not moved.stats.errors
    health = moved.health_extra()["layout"]
    assert health["cellmap"] == moved_cutout and health["cutouts"] == {"palm": MOVED}
    assert health["cells"]["palm"] == 30 and shipped.health_extra()["layout"]["cutouts"] == {"palm": SHIPPED}
    frame = SimpleNamespace(tx_mask=0xFFFF, rx_mask=0x3F, sequence=7, imu=None,
                            impedance=np.ones((16, 16), np.complex64))
    service._on_frame(frame, np.full((16, 16), 5.0, np.float32), 1.0)
    msg = moved.outputs["tactile"][-1]
    mask = np.asarray(msg.mask).reshape(16, 16)
    assert mask[tuple(np.array(MOVED).T)].sum() == 0 and mask[tuple(np.array(SHIPPED).T)].all()
    assert np.asarray(msg.pressure).reshape(16, 16)[4, 0] == 0 and np.asarray(msg.pressure).reshape(16, 16)[4, 3] == 5
    default_mask = cell_mask(glove_layout.default(), 0xFFFF, 0x3F).reshape(16, 16)
    assert (default_mask != mask).sum() == 12


def test_another_cutout_changes_what_the_tactile_projection_samples(moved_cutout):
    shipped = TactileProjector()
    moved = TactileProjector(shipped.template, glove_layout.load(moved_cutout))
    on_palm = shipped.template.chain == PALM_CHAIN
    near_old = on_palm & (np.abs(shipped.rc[:, 0] - 4.5) < 0.4) & (np.abs(shipped.rc[:, 1] - 4.0) < 0.4)
    near_new = on_palm & (np.abs(shipped.rc[:, 0] - 4.5) < 0.4) & (np.abs(shipped.rc[:, 1] - 1.0) < 0.4)
    assert near_old.any() and near_new.any()
    assert not shipped.sensed[near_old].any() and shipped.sensed[near_new].all()
    assert moved.sensed[near_old].all() and not moved.sensed[near_new].any()
    p = np.zeros((16, 16))
    p[4:6, 3:6] = 20.0  # pressed where the moved cutout's palm has cells
    assert np.all(moved.sample(p)[near_old] > 15)  # bicubic: near, not at, the cells' value
    assert np.all(shipped.sample(p)[near_old] == 0)


def test_recon_reads_its_cell_map_parameter(moved_cutout):
    node = FakeNode("main")
    service = ReconService(node, ReconService.Params(detector="simulated", cellmap=moved_cutout))
    assert service.projector.layout.path == moved_cutout and "tactile" in node.handlers
    assert node.health_extra()["layout"]["cutouts"] == {"palm": MOVED}


def _variants(tmp_path) -> dict[str, tuple[str, str]]:
    """Broken copies of the shipped cell map: file name -> (its text, the problem it must name)."""
    good = json.loads(DEFAULT_CELLMAP.read_text())
    out: dict[str, tuple[str, str]] = {"truncated.json": (DEFAULT_CELLMAP.read_text()[:500], "not JSON")}

    def variant(name: str, problem: str, change) -> None:
        d = copy.deepcopy(good)
        change(d)
        out[name] = (json.dumps(d), problem)

    variant("shape.json", "the region matrix is (15, 16), the readout matrix (16, 16)",
            lambda d: d["region"].pop())
    variant("small.json", "a 8x8 readout matrix",  # the palm alone on an 8 x 8 module
            lambda d: d.update(matrix={"rows": 8, "cols": 8, "tx_mask": 0x3F, "rx_mask": 0x3F},
                               sensors=d["sensors"][:1],
                               region=[[v if v == PALM else -1 for v in r[:8]] for r in d["region"][:8]]))
    variant("twice.json", "thumb: cell (0, 0) is also palm's",
            lambda d: d["sensors"][1]["cells"][0].update(row=0, col=0))
    variant("masks.json", "tx_mask/rx_mask 0xffff/0xff disagree", lambda d: d["matrix"].update(rx_mask=0xFF))
    variant("region.json", "the region matrix disagrees with the sensors' cells (first at crossing (4, 3))",
            lambda d: d["region"][4].__setitem__(3, PALM))
    variant("cutout.json", "palm: its cells are not its 6x6 block", lambda d: d["sensors"][0].update(cutouts=[]))
    last = len(TACTILE_REGIONS) - 1
    variant("block.json", "little: its 2x6 block at row 15, column 0 runs outside the 16x16 readout matrix",
            lambda d: d["sensors"][5].update(row0=15))
    variant("order.json", "a glove's are", lambda d: d.update(  # consistent, but not the glove's region order
        regions=d["regions"][::-1], region=[[v if v < 0 else last - v for v in r] for r in d["region"]]))
    variant("format.json", "not a crossmodal-skin-cellmap version 1 file", lambda d: d.update(version=2))
    variant("keys.json", "a field is missing", lambda d: d["sensors"][2].pop("row0"))
    return out


def test_broken_cell_maps_are_refused_naming_the_file_and_the_problem(tmp_path):
    with pytest.raises(CellMapError, match="missing.json: cannot read it"):
        glove_layout.load(tmp_path / "missing.json")
    for name, (text, problem) in _variants(tmp_path).items():
        (tmp_path / name).write_text(text)
        with pytest.raises(CellMapError) as e:
            glove_layout.load(tmp_path / name)
        assert name in str(e.value) and problem in str(e.value), (name, str(e.value))


def test_the_services_refuse_a_broken_cell_map_at_start_and_say_so(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(_variants(tmp_path)["twice.json"][0])
    node = FakeNode()
    service = glove(node, str(bad))
    assert node.status == "error" and "bad.json" in node.message and "is also palm's" in node.message
    assert node.stats.errors["bad_cellmap"] == 1 and service.driver is None
    assert "bad.json" in node.health_extra()["layout"]["error"] and "link" not in node.health_extra()
    node = FakeNode("main")
    recon = ReconService(node, ReconService.Params(detector="simulated", cellmap=str(bad)))
    assert node.status == "degraded" and "bad.json" in node.message and recon.projector is None
    assert node.stats.errors["bad_cellmap"] == 1 and "tactile" not in node.handlers
    assert "bad.json" in node.health_extra()["layout"]["error"]
