"""Sensor-skin fabrication (skin/unwrap.py, nest.py, toolpath.py, cli.py): the stretch-minimizing
unwrap against LSCM on the glove's finger parts, exact nesting margins, the annealer against
bottom-left fill, SVG toolpaths in mm, and ``xm skin`` end to end and on bad input."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh
from shapely import Polygon, box, distance

from skin import examples
from skin.cli import main
from skin.errors import SkinError
from skin.layout import place
from skin.nest import Piece, anneal, bottom_left_fill
from skin.toolpath import contours, order, travel_in_given_order, write_svg
from skin.unwrap import distortion, kabsch_2d, lscm, stretch_minimizing

SVG = "{http://www.w3.org/2000/svg}"


def test_kabsch_2d_recovers_a_rotation_and_never_mirrors():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(5, 3, 2))
    ang = rng.uniform(-np.pi, np.pi, 5)
    R = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], -2)
    np.testing.assert_allclose(kabsch_2d(src, np.einsum("fij,fkj->fki", R, src)), R, atol=1e-9)
    mirrored = src * [1, -1]  # the best proper rotation onto a mirror image is still a rotation
    assert np.allclose(np.linalg.det(kabsch_2d(src, mirrored)), 1.0)


def test_a_developable_part_unwraps_without_stretch():
    cyl = trimesh.creation.cylinder(radius=10, height=20, sections=48)
    keep = (np.abs(cyl.face_normals[:, 2]) < 0.5) & (cyl.triangles_center[:, 1] < 0)  # half the side
    part = cyl.submesh([np.flatnonzero(keep)], append=True)
    u = stretch_minimizing(part.vertices, part.faces, "half cylinder")
    d = distortion(part.vertices, u.uv, part.faces)
    assert d["edge_max"] < 1e-3 and d["flipped"] == 0


@pytest.mark.parametrize("finger", ["thumb", "index", "middle", "ring", "little"])
def test_finger_parts_unwrap_with_a_third_of_lscms_stretch_and_no_flips(finger):
    spec, carrier, surface = next(s for s in examples.glove().sensors if s[0].name == finger)
    p = place(spec, carrier, surface)
    ours = distortion(p.vertices, stretch_minimizing(p.vertices, p.faces, finger).uv, p.faces)
    theirs = distortion(p.vertices, lscm(p.vertices, p.faces, finger), p.faces)
    assert ours["flipped"] == 0
    assert theirs["edge_mean"] >= 3.0 * ours["edge_mean"], (ours["edge_mean"], theirs["edge_mean"])


def _pieces() -> list[Piece]:
    """Non-convex parts: L shapes, a comb, a plate with a hole, strips."""
    ell = Polygon([(0, 0), (40, 0), (40, 10), (10, 10), (10, 30), (0, 30)])
    comb = box(0, 0, 50, 6).union(box(0, 0, 6, 25)).union(box(22, 0, 28, 25)).union(box(44, 0, 50, 25))
    plate = box(0, 0, 30, 30).difference(box(10, 10, 20, 20))
    return ([Piece(f"ell{i}", ell) for i in range(3)] + [Piece("comb", comb), Piece("plate", plate)]
            + [Piece(f"strip{i}", box(0, 0, 45, 5)) for i in range(3)])


def test_nestings_keep_the_margin_exactly_and_stay_on_the_sheet():
    pieces = _pieces()
    for n in (anneal(pieces, 2.0, (150, 150), 800, seed=1), bottom_left_fill(pieces, 2.0, 120, 150)):
        gaps = [distance(a, b) for i, a in enumerate(n.shapes) for b in n.shapes[i + 1:]]
        assert min(gaps) >= 2.0 - 1e-9 and abs(min(gaps) - n.min_gap) < 1e-9
        lo = np.min([s.bounds[:2] for s in n.shapes], axis=0)
        hi = np.max([s.bounds[2:] for s in n.shapes], axis=0)
        assert (hi - lo <= [150, 150]).all()
        for p, s in zip(pieces, n.shapes, strict=True):
            assert abs(p.shape.area - s.area) < 1e-6, "pieces move rigidly"


def test_annealing_packs_within_15_percent_of_bottom_left_fills_best():
    pieces = _pieces()
    blf = min(bottom_left_fill(pieces, 2.0, w, 300).area for w in (80, 100, 120))
    sa = anneal(pieces, 2.0, (200, 300), 3000, seed=0)
    assert sa.loss[-1][1] <= sa.loss[0][0], "annealing never ends worse than it started"
    assert sa.area <= 1.15 * blf, (sa.area, blf)


def test_parts_that_cannot_be_nested_are_named():
    with pytest.raises(SkinError, match="wide: the part \\(250.0 x 5.0 mm\\) does not fit the 200 x 100 mm sheet"):
        anneal([Piece("ok", box(0, 0, 10, 10)), Piece("wide", box(0, 0, 250, 5))], 2.0, (200, 100), 10)
    many = [Piece(f"tile{i}", box(0, 0, 45, 45)) for i in range(12)]
    with pytest.raises(SkinError, match="sheet: the parts with their margins need"):
        anneal(many, 2.0, (100, 100), 10)
    big = [Piece(f"big{i}", box(0, 0, 55, 55)) for i in range(3)]  # area would do; shapes cannot
    with pytest.raises(SkinError, match="big1: no free place left"):
        bottom_left_fill(big, 2.0, 100, 100)


def test_toolpaths_are_closed_paths_in_mm_holes_first_ordered_for_short_travel(tmp_path):
    n = bottom_left_fill(_pieces(), 2.0, 120, 150)
    stats = write_svg(tmp_path / "layer.svg", n.shapes, n.names, "electrodes")
    root = ET.parse(tmp_path / "layer.svg").getroot()
    W, H = float(root.get("width")[:-2]), float(root.get("height")[:-2])
    assert root.get("width").endswith("mm") and root.get("viewBox") == f"0 0 {W:.3f} {H:.3f}"
    paths = root.findall(f"{SVG}g/{SVG}path")
    assert len(paths) == stats["paths"] == sum(len(r) for s in n.shapes for r in contours(s))
    labels = [p.get("{http://www.inkscape.org/namespaces/inkscape}label") for p in paths]
    hole, outline = [i for i, lab in enumerate(labels) if lab == "plate"]
    assert hole < outline, "the plate's hole is cut before its outline"
    pts = np.array([[float(v) for v in xy.split(",")] for p in paths for xy in p.get("d")[2:-2].split(" L ")])
    assert (pts >= 0).all() and (pts <= [W, H]).all()
    assert all(p.get("d").endswith("Z") for p in paths)
    assert stats["travel_mm"] <= stats["travel_unordered_mm"]
    groups = [g for s in n.shapes for g in contours(s)][::-1]
    assert order(groups)[1] <= travel_in_given_order(groups)


def test_svg_shows_parts_from_their_outer_side(tmp_path):
    """A counter-clockwise part (seen from outside) keeps its handedness on the sheet: an L whose
    foot points to +x in the flat points to +x in the SVG, and its leg up (-y in SVG units)."""
    ell = Polygon([(0, 0), (40, 0), (40, 10), (10, 10), (10, 30), (0, 30)])
    write_svg(tmp_path / "l.svg", [ell], ["ell"], "cut")
    d = ET.parse(tmp_path / "l.svg").getroot().find(f"{SVG}g/{SVG}path").get("d")
    pts = np.array([[float(v) for v in xy.split(",")] for xy in d[2:-2].split(" L ")])
    area = 0.5 * np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1])
    assert area < 0, "counter-clockwise in the flat reads clockwise in y-down SVG units (same handedness on screen)"


def test_xm_skin_fingertip_writes_every_file(tmp_path, capsys):
    assert main(["fingertip", "--out", str(tmp_path), "--iterations", "300"]) == 0
    for suffix in ("base.obj", "parts.obj", "cellmap.json", "electrodes.svg", "dielectric.svg", "markers.svg",
                   "distortion.png", "nesting_loss.png", "layout.png"):
        assert (tmp_path / f"fingertip_{suffix}").stat().st_size > 0, suffix
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["parts"]["fingertip"]["ours"]["flipped"] == 0
    assert rep["nesting"]["electrodes"]["min_gap_mm"] >= 2.0 and rep["nesting"]["electrodes"]["pieces"] == 3
    assert "fingertip: edge distortion" in capsys.readouterr().out


def test_xm_skin_names_the_bad_mesh_and_fails_cleanly(tmp_path, capsys):
    box_mesh = trimesh.creation.box((20, 20, 20))
    trimesh.Trimesh(box_mesh.vertices, box_mesh.faces[:-1], process=False).export(tmp_path / "holed.obj")
    rc = main(["design", str(tmp_path / "holed.obj"), "--rows", "2", "--cols", "2", "--pitch", "4",
               "--centre", "0,0,10", "--normal", "0,0,1", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "holed.obj: open mesh" in err and "open_mesh" in err
    box_mesh.export(tmp_path / "cube.obj")
    rc = main(["design", str(tmp_path / "cube.obj"), "--rows", "20", "--cols", "20", "--pitch", "5",
               "--centre", "0,0,10", "--normal", "0,0,1", "--out", str(tmp_path / "out")])
    assert rc == 2 and "cube: the layout does not fit the surface" in capsys.readouterr().err
