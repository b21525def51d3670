"""Glove layout, simulated sensor and per-cell calibration (thesis 4.5.6, 4.8)."""

from __future__ import annotations

import numpy as np
import pytest

from services.glove.calibration import Calibration, fit_linear, fit_rational, plot_fit, rational, report
from services.glove.layout import (
    CELL_MASK,
    CELL_REGION,
    CELLS_PER_REGION,
    RX_MASK,
    TX_MASK,
    region_means,
    region_pressure_kpa,
)
from services.glove.sensor_model import GloveSensorModel, nominal_calibration
from shared.demo import TACTILE_REGIONS
from shared.protocols import tactile


def test_layout_has_five_fingers_and_a_palm_with_a_cutout_inside_the_masks():
    assert CELL_MASK.dtype == np.uint8 and CELL_REGION.shape == (16, 16)
    assert CELLS_PER_REGION[TACTILE_REGIONS.index("palm")] == 36 - 6
    assert all(CELLS_PER_REGION[i] == 12 for i in range(5))
    rows, cols = np.nonzero(CELL_MASK)
    assert all(TX_MASK >> r & 1 for r in rows) and all(RX_MASK >> c & 1 for c in cols)
    assert np.all(CELL_REGION[CELL_MASK == 0] == -1)
    p = np.where(CELL_REGION == TACTILE_REGIONS.index("ring"), 4.0, 0.0)
    np.testing.assert_allclose(region_means(p), [0, 0, 0, 4.0, 0, 0])


def test_simulated_glove_through_the_wire_and_nominal_calibration_gives_region_pressure():
    model = GloveSensorModel(3)
    cal = nominal_calibration(3)
    forces = np.array([2.0, 6.0, 0.0, 1.0, 0.0, 10.0])
    dec = tactile.StreamDecoder()
    got = []
    for i in range(20):
        got += dec.feed(tactile.encode_frame(model.frame(forces, i * 1e-3, i)))
    assert len(got) == 20 and dec.stats["sequence_gaps"] == 0
    assert len(tactile.encode_frame(model.frame(forces, 0.0, 0))) == 423
    means = np.mean([region_means(cal.pressure(f.impedance)) for f in got], axis=0)
    truth = region_pressure_kpa(forces)
    # Noise, drift and neighbour crosstalk: within 0.3 kPa + 10 %.
    assert np.all(np.abs(means - truth) <= 0.3 + 0.1 * truth), (means, truth)
    assert means[2] < 0.3 and means[4] < 0.3


def test_fit_rational_recovers_parameters_and_beats_linear():
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 60, 400)
    r = rational(p, 0.02, 0.01) + rng.normal(0, 1e-4, p.size)
    a, b = fit_rational(p, r)
    assert abs(a - 0.02) < 5e-4 and abs(b - 0.01) < 5e-4
    slope, offset = fit_linear(p, r)
    lin_err = np.abs(slope * p + offset - r).max()
    assert np.abs(rational(p, a, b) - r).max() < 0.1 * lin_err


def test_report_figures_as_in_thesis_4_8_4(tmp_path):
    p = np.linspace(0, 50, 200)
    r = rational(p, 0.02, 0.01)
    pred = r / (0.02 - 0.01 * r)  # inverting the exact model
    rep = report(p, pred, r)
    assert rep["correlation"] > 0.9999 and rep["samples"] == 200
    assert 0.05 < rep["relative_nonlinearity"] < 0.2  # a saturating response is visibly non-linear
    assert report(p, p, 3 * p + 1)["relative_nonlinearity"] < 1e-9
    plot_fit(p, r, 0.02, 0.01, tmp_path / "fit.png", "cell")
    assert (tmp_path / "fit.png").stat().st_size > 1000


def test_calibration_save_load_round_trip_and_bad_file(tmp_path):
    cal = nominal_calibration(1)
    cal.save(tmp_path / "c.json")
    back = Calibration.load(tmp_path / "c.json")
    z = GloveSensorModel(1).impedance(np.full(6, 3.0), 0.0)
    np.testing.assert_array_equal(back.pressure(z), cal.pressure(z))
    assert back.pressure(z).dtype == np.float32 and np.all(back.pressure(z)[CELL_MASK == 0] == 0)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="not a glove calibration"):
        Calibration.load(tmp_path / "bad.json")
