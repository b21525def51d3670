"""Sensor-skin layout (skin/layout.py, examples.py, cellmap.py, mesh.py): the glove's and the
fingertip's matrices on their base meshes, the glove's cell map (the shipped one is what the
skin tools write; it round-trips into the glove service's layout and the tactile projection),
even electrode spacing, and bad input naming the part."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from shapely import distance

from services.glove import layout as glove_layout
from services.glove.layout import DEFAULT_CELLMAP
from services.recon.hand_mesh import pose
from services.recon.tactile_projection import TactileProjector
from skin import cellmap, examples
from skin.cli import plane_carrier
from skin.errors import COUNTS, SkinError
from skin.layout import SensorSpec, flat_parts, place
from skin.mesh import check_sheet, load_base_mesh
from skin.unwrap import stretch_minimizing


@pytest.fixture(scope="module")
def glove():
    d = examples.glove()
    return d, [place(s, c, m) for s, c, m in d.sensors]


def _without_geometry(d: dict) -> dict:
    return {**d, "sensors": [{**s, "cells": [[c["row"], c["col"]] for c in s["cells"]]} for s in d["sensors"]]}


def test_the_shipped_glove_cell_map_is_what_the_skin_tools_write(glove, tmp_path):
    """models/skin/glove_cellmap.json, the glove service's default layout, is the skin tools' glove
    (`make cellmap`): the same cells, and the same positions and normals on the hand."""
    design, placements = glove
    path = tmp_path / "glove_cellmap.json"
    cellmap.cell_map(design, placements).save(path)
    made, shipped = json.loads(path.read_text()), json.loads(DEFAULT_CELLMAP.read_text())
    assert _without_geometry(made) == _without_geometry(shipped)
    rc, pos, normal = cellmap.load(path).positions()
    rc0, pos0, normal0 = cellmap.load(DEFAULT_CELLMAP).positions()
    np.testing.assert_array_equal(rc, rc0)
    np.testing.assert_allclose(pos, pos0, atol=1e-3)
    np.testing.assert_allclose(normal, normal0, atol=1e-4)
    assert np.allclose(np.linalg.norm(normal, axis=1), 1, atol=1e-3)


def test_glove_cell_map_round_trips_into_the_glove_services_layout(glove, tmp_path):
    design, placements = glove
    path = tmp_path / "glove_cellmap.json"
    cellmap.cell_map(design, placements).save(path)
    m, lay = cellmap.load(path), glove_layout.load(path)
    np.testing.assert_array_equal(lay.region, m.region_matrix())
    assert (lay.tx_mask, lay.rx_mask) == (m.tx_mask(), m.rx_mask()) == (0xFFFF, 0x3F)
    np.testing.assert_array_equal(lay.cells_per_region, [12, 12, 12, 12, 12, 30])
    assert lay.cutouts() == {"palm": [[4, 3], [4, 4], [4, 5], [5, 3], [5, 4], [5, 5]]}


def test_every_glove_cell_lies_where_the_tactile_projection_reads_that_cell(glove):
    """A cell's centre on the hand, looked up on the projection's hand surface (same keypoints),
    carries that cell's (row, col) readout coordinate (within a tenth of a cell)."""
    design, placements = glove
    m = cellmap.cell_map(design, placements)
    proj = TactileProjector()  # the shipped cell map's layout
    verts = pose(examples.hand_keypoints(), "right", proj.template)
    faces = proj.template.faces("right")
    region = m.region_matrix()
    rc, pos, _ = m.positions()
    for k in np.unique(region[region >= 0]):
        own = rc[region[rc[:, 0], rc[:, 1]] == k]
        at = pos[region[rc[:, 0], rc[:, 1]] == k] / examples.MM
        f = faces[(proj.region[faces] == k).all(axis=1)]
        q, dist, tri = trimesh.proximity.closest_point(trimesh.Trimesh(verts, f, process=False), at)
        bc = trimesh.triangles.points_to_barycentric(verts[f[tri]], q)
        read = np.einsum("nk,nkj->nj", bc, proj.rc[f[tri]])
        assert dist.max() < 0.002, f"region {k}: cells lie {dist.max() * 1e3:.1f} mm off the hand surface"
        np.testing.assert_allclose(read, own, atol=0.1, err_msg=f"region {k}: cells read at other coordinates")


def test_the_fingertip_matrix_wraps_the_tip_at_45_degrees():
    d = examples.fingertip()
    p = place(*d.sensors[0])
    pos = {tuple(c): x for c, x in zip(p.cells, p.cell_position, strict=True)}
    assert len(pos) == 16
    assert pos[(3, 3)][2] == max(x[2] for x in pos.values()), "one corner at the tip"
    assert pos[(0, 0)][2] == min(x[2] for x in pos.values()), "one at the base"
    assert pos[(0, 3)][0] * pos[(3, 0)][0] < 0 and abs(pos[(0, 3)][2] - pos[(3, 0)][2]) < 1e-6, \
        "two at the sides, level with each other"
    r = np.linalg.norm(p.cell_position[:, :2], axis=1)
    on_cylinder = p.cell_position[:, 2] <= examples.FINGERTIP_LENGTH / 2
    np.testing.assert_allclose(r[on_cylinder], examples.FINGERTIP_RADIUS, atol=0.05)


def test_electrodes_are_evenly_separated_and_the_cutout_shortens_its_lines(glove):
    _, placements = glove
    palm = placements[0]
    u = stretch_minimizing(palm.vertices, palm.faces, "palm", iterations=60, refine=30)
    f = flat_parts(palm, u.uv)
    gaps = [distance(f.rows[i], f.rows[i + 1]) for i in range(5)] + [distance(f.cols[i], f.cols[i + 1])
                                                                      for i in range(5)]
    np.testing.assert_allclose(gaps, palm.spec.gap, rtol=0.1)
    assert f.rows[4].area < 0.6 * f.rows[0].area and f.cols[4].area < 0.75 * f.cols[0].area
    assert all(f.outline.contains(s) for s in f.rows + f.cols), "electrodes lie inside the part"
    assert len(f.conductors) == 12 and all(c.area > 0 for c in f.conductors)


def test_open_and_non_manifold_meshes_are_refused_naming_the_file(tmp_path):
    box = trimesh.creation.box((10, 10, 10))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    open_box.export(tmp_path / "open.stl")
    with pytest.raises(SkinError, match="open.stl: open mesh") as e:
        load_base_mesh(tmp_path / "open.stl")
    assert e.value.reason == "open_mesh"
    fin = trimesh.Trimesh(np.vstack([box.vertices, [[0, 0, 20]]]),
                          np.vstack([box.faces, [[0, 1, 8]]]), process=False)  # a fin on an edge
    fin.export(tmp_path / "fin.obj")
    before = COUNTS["non_manifold"]
    with pytest.raises(SkinError, match="fin.obj: non-manifold"):
        load_base_mesh(tmp_path / "fin.obj")
    assert COUNTS["non_manifold"] == before + 1
    (tmp_path / "junk.ply").write_text("not a mesh")
    with pytest.raises(SkinError, match="junk.ply"):
        load_base_mesh(tmp_path / "junk.ply")


def test_parts_to_unwrap_must_be_open_sheets():
    sphere = trimesh.creation.icosphere(2)
    with pytest.raises(SkinError, match="cap: the part is closed"):
        check_sheet(sphere.vertices, sphere.faces, "cap")
    two = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([5, 0, 0])])
    half = two.faces[two.triangles_center[:, 2] > 0]
    with pytest.raises(SkinError, match="pair: the part falls apart"):
        check_sheet(two.vertices, half, "pair")


def test_a_layout_that_does_not_fit_the_surface_names_the_sensor():
    d = examples.fingertip()
    big = SensorSpec("oversized", "sensor", 8, 8)
    carrier = plane_carrier(np.array([0.0, -8.0, 0.0]), np.array([0.0, -1.0, 0.0]), (80.0, 80.0), 0.0)
    with pytest.raises(SkinError, match="oversized: the layout does not fit the surface") as e:
        place(big, carrier, d.base)
    assert e.value.reason == "does_not_fit"
    split = SensorSpec("split", "sensor", 3, 3, cutouts=((1, 1, 1, 1),))
    with pytest.raises(SkinError, match="split: a cutout cuts row 1's electrode in two"):
        place(split, d.sensors[0][1], d.base)


def test_a_cell_map_with_clashing_cells_is_refused(glove, tmp_path):
    design, placements = glove
    data = cellmap.cell_map(design, placements).to_json()
    data["sensors"][1]["cells"][0]["row"] = 0  # the thumb claims a palm crossing
    data["sensors"][1]["cells"][0]["col"] = 0
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SkinError, match="thumb: cell \\(0, 0\\) is also palm's"):
        cellmap.load(path)
