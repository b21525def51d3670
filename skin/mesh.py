"""Base meshes and part meshes: loading through trimesh and the topology checks the tools rely on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from skin.errors import SkinError


def edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E,2) of triangles and how many faces share each."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def check_closed(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    """A base mesh must be closed and manifold (every edge on exactly two faces, consistent winding)."""
    if len(mesh.faces) == 0:
        raise SkinError("empty_mesh", name, "the mesh has no faces")
    _, count = edge_counts(np.asarray(mesh.faces))
    if (count > 2).any():
        raise SkinError("non_manifold", name, f"non-manifold mesh: {(count > 2).sum()} edges shared by more than "
                        "two faces")
    if (count < 2).any():
        raise SkinError("open_mesh", name, f"open mesh: {(count < 2).sum()} boundary edges (a base mesh must be "
                        "closed)")
    if not mesh.is_winding_consistent:
        raise SkinError("non_manifold", name, "inconsistent face winding (non-orientable or flipped faces)")
    return mesh


def load_base_mesh(path: str | Path) -> trimesh.Trimesh:
    """An OBJ / STL / PLY base mesh (mm), checked closed and manifold; errors name the file."""
    name = Path(path).name
    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise SkinError("unreadable_mesh", name, f"cannot read the mesh ({exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise SkinError("unreadable_mesh", name, "the file holds no triangle mesh")
    return check_closed(mesh, name)


def check_sheet(vertices: np.ndarray, faces: np.ndarray, name: str) -> list[np.ndarray]:
    """A part to unwrap must be one connected manifold sheet of genus 0: every edge on one or two
    faces, at least one boundary loop (a disk, or a disk with holes such as a cutout). Returns the
    boundary loops' vertex ids, the longest (the outline) first."""
    if len(faces) == 0:
        raise SkinError("empty_mesh", name, "the part has no faces")
    edges, count = edge_counts(faces)
    if (count > 2).any():
        raise SkinError("non_manifold", name, f"non-manifold part: {(count > 2).sum()} edges shared by more than "
                        "two faces")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if len(trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(faces)))) != 1:
        raise SkinError("not_a_sheet", name, "the part falls apart into several pieces; unwrap each on its own")
    boundary = edges[count == 1]
    if len(boundary) == 0:
        raise SkinError("closed_part", name, "the part is closed; cut it open before unwrapping")
    loops = _boundary_loops(boundary)
    if loops is None:
        raise SkinError("non_manifold", name, "pinched boundary: a vertex where more than two boundary edges meet")
    euler = len(np.unique(faces)) - len(edges) + len(faces)
    if euler != 2 - len(loops):
        raise SkinError("not_a_sheet", name, f"the part has handles or pinched vertices (Euler characteristic "
                        f"{euler} with {len(loops)} boundary loops); cut it into disks")
    return sorted(loops, key=len, reverse=True)


def _boundary_loops(boundary: np.ndarray) -> list[np.ndarray] | None:
    """Boundary edges (B,2) chained into closed loops of vertex ids; None where a vertex is pinched
    (more than two boundary edges meet there)."""
    nxt: dict[int, list[int]] = {}
    for a, b in boundary:
        nxt.setdefault(int(a), []).append(int(b))
        nxt.setdefault(int(b), []).append(int(a))
    if any(len(v) != 2 for v in nxt.values()):
        return None
    seen: set[int] = set()
    loops = []
    for start in nxt:
        if start in seen:
            continue
        loop, prev, cur = [start], -1, start
        seen.add(start)
        while True:
            cand = [v for v in nxt[cur] if v != prev]
            nxt_v = cand[0]
            if nxt_v == start:
                break
            prev, cur = cur, nxt_v
            loop.append(cur)
            seen.add(cur)
        loops.append(np.array(loop))
    return loops
