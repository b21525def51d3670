"""Tactile glove: readout protocol decoding, calibration, crosstalk compensation, publication."""
