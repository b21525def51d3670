"""The simulated cameras: exact intrinsics, readout windows, what the hands look like, lighting
per session (services/world/render.py, services/world/appearance.py)."""

from __future__ import annotations

import numpy as np
import pytest

from services.world import appearance
from services.world.render import SceneRenderer, Snapshot, gl_frustum
from services.world.sim import WorldSim

W, H = 160, 120


@pytest.fixture(scope="module")
def rig():
    sim = WorldSim("assembly", seed=0)
    renderer = SceneRenderer("assembly", W, H)
    hand_ids = renderer._hand_mocap  # (2, 21) mocap indices of the keypoints
    yield sim, renderer, hand_ids
    renderer.close()


def snap_with_hands(sim: WorldSim, hand_ids: np.ndarray, left: np.ndarray | None, right: np.ndarray | None,
                    seed: int = 0, glove: str = "left") -> Snapshot:
    mocap = sim.data.mocap_pos.copy()
    for i, where in enumerate((left, right)):
        mocap[hand_ids[i]] = [0.0, 0.0, -1.0] if where is None else where  # None: parked out of the cell
    return Snapshot("assembly", 0.0, sim.data.qpos.copy(), mocap, sim.data.mocap_quat.copy(), seed=seed,
                    glove_hand=glove)


def blob(renderer, snap_a: Snapshot, snap_b: Snapshot, cam: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N,2) as (u, v) and their colours where two renders differ."""
    a = renderer.render(snap_a)[cam].astype(int)
    b = renderer.render(snap_b)[cam].astype(int)
    v, u = np.nonzero(np.abs(a - b).sum(axis=2) > 30)
    return np.stack([u, v], axis=1), b[v, u]


def test_a_sphere_lands_on_the_pixel_its_intrinsics_project_it_to(rig):
    sim, _, ids = rig
    renderer = SceneRenderer("assembly", 640, 480)  # the sphere spans ~30 px: its centroid is measurable
    X = np.array([0.05, -0.04, 0.12])
    empty = snap_with_hands(sim, ids, None, None)
    # All 21 keypoints at X: the hand draws as one sphere (gloved: dark on the light table).
    with_ball = snap_with_hands(sim, ids, None, X, glove="right")
    try:
        for c, cam in enumerate(renderer.cameras):
            pix, _ = blob(renderer, empty, with_ball, c)
            assert len(pix) > 50, f"{cam.name}: {len(pix)} pixels"
            x = np.linalg.inv(cam.world_T_cam) @ [*X, 1.0]
            uv = (cam.K @ x[:3] / x[2])[:2]
            assert np.linalg.norm(pix.mean(axis=0) - uv) < 0.5, f"{cam.name}: centroid {pix.mean(axis=0)} vs {uv}"
    finally:
        renderer.close()


def test_a_window_renders_exactly_that_part_of_the_full_image(rig):
    sim, renderer, _ = rig
    sim.reset(0)
    sim.step(1000)
    from services.world.render import snapshot

    snap = snapshot("assembly", sim.data, "workcell", 0, sim.demo, "left")
    full = renderer.render(snap)
    window = (40, 30, 64, 50)
    parts = renderer.render(snap, [window] * len(renderer.cameras))
    for f, p in zip(full, parts, strict=True):
        assert p.shape == (50, 64, 3)
        assert np.abs(f[30:80, 40:104].astype(int) - p).mean() < 0.5


def test_the_gloved_hand_wears_the_glove_colour_and_the_other_shows_skin(rig):
    sim, renderer, ids = rig
    from services.world.teacher import Teacher

    hands = Teacher("assembly", 0).state(0.5).hands
    empty = snap_with_hands(sim, ids, None, None)
    cam = renderer.cameras[1]
    x = np.linalg.inv(cam.world_T_cam) @ [*hands[0][[0, 5, 9, 13, 17]].mean(axis=0), 1.0]
    palm = (cam.K @ x[:3] / x[2])[:2]  # the back of the hand, away from the sleeve

    def palm_colour(glove: str) -> np.ndarray:
        pix, rgb = blob(renderer, empty, snap_with_hands(sim, ids, hands[0], None, glove=glove), 1)
        near = np.linalg.norm(pix - palm, axis=1) < 4
        assert near.sum() >= 5
        return rgb[near].mean(axis=0) / 255

    glove, skin = palm_colour("left"), palm_colour("right")
    assert glove.sum() < skin.sum(), "the glove's fabric is darker than skin"
    assert skin[0] > skin[2] and glove[2] >= glove[0], f"skin is red-brown {skin}, the glove blue-grey {glove}"


def test_lighting_changes_between_sessions_and_repeats_within_one(rig):
    sim, renderer, ids = rig
    images = {s: renderer.render(snap_with_hands(sim, ids, None, None, seed=s))[0].astype(int) for s in (0, 1)}
    again = renderer.render(snap_with_hands(sim, ids, None, None, seed=0))[0].astype(int)
    assert np.array_equal(images[0], again)
    assert np.abs(images[0] - images[1]).mean() > 3
    a, b = appearance.session_lighting(0, 0), appearance.session_lighting(0, 1)
    assert not np.allclose(a.dir, b.dir) and not np.allclose(a.diffuse, b.diffuse), "each demonstration its light"


def test_hand_capsules_draw_a_hand_and_nothing_for_a_parked_or_broken_one():
    from services.world.teacher import Teacher

    k = Teacher("assembly", 0).state(0.5).hands[1]
    caps = appearance.hand_capsules(k, appearance.SKIN_TONES[0], appearance.SLEEVES[0])
    shades = {c.rgba for c in caps}
    assert len(caps) == len(appearance.PALM_BONES) + 5 * 3 + 1 and len(shades) >= 4, "phalanges shaded apart"
    assert appearance.hand_capsules(np.full((21, 3), [0, 0, -1.0]), appearance.GLOVE_COLOR) == []
    broken = k.copy()
    broken[3] = np.nan
    assert appearance.hand_capsules(broken, appearance.GLOVE_COLOR) == []


def test_frustum_of_the_full_window_is_centred_on_the_principal_point():
    K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])
    center, half, bottom, top = gl_frustum(K, (0, 0, 160, 120), near=1.0)
    assert center == pytest.approx(0.0) and bottom == pytest.approx(-top)
    assert half == pytest.approx(80 / 200) and top == pytest.approx(60 / 200)
