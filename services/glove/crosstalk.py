"""Crosstalk in resistive sensor matrices and its compensation (thesis 4.3, 4.3.1) (pure).

Readout model: one excitation line i at a time is driven to V; the other excitation lines are
held at ground; every reception line j is tied to ground through a reference resistor R_ref and
its voltage v_ij is measured. Cell (k, j) is a resistor with conductance G_kj (pressure lowers
its resistance). Current from the driven line into column j leaks to ground through R_ref AND
through every other cell of that column (the crosstalk):

    (V - v_ij) G_ij = v_ij (G_ref + sum_{k != i} G_kj)

so a press on one cell changes the readings of the other cells in its column. Compensation
recovers G from all 16x16 readings by the fixed-point iteration G <- v (G_ref + S) / V with the
column sums S = sum_k G_kj, starting from the naive G = v G_ref / V (no crosstalk). The iteration
converges linearly with rate sum_i v_ij / V (slow when a column is pressed hard); summing the
fixed-point equation over a column gives its limit in closed form, S_j = G_ref s_j / (1 - s_j)
with s_j = sum_i v_ij / V, which ``compensate`` uses as its starting point.

``network_readings`` solves the full resistor network by nodal analysis (any set of driven lines,
the others grounded) as an independent check of the forward model; ``direct`` solves the same
inverse problem as one linear system per column (the baseline in bench/crosstalk.py).
"""

from __future__ import annotations

import numpy as np


def readings(G: np.ndarray, g_ref: float, v_drive: float = 1.0) -> np.ndarray:
    """Column voltages (rows x cols) for a conductance matrix: the forward model."""
    S = G.sum(axis=0, keepdims=True)
    return v_drive * G / (G + g_ref + (S - G))


def naive(v: np.ndarray, g_ref: float, v_drive: float = 1.0) -> np.ndarray:
    """Ignoring crosstalk: each reading as a simple voltage divider with R_ref."""
    return v * g_ref / np.maximum(v_drive - v, 1e-12)


def compensate(v: np.ndarray, g_ref: float, v_drive: float = 1.0, iterations: int = 50,
               tol: float = 1e-10, closed_form_start: bool = True) -> np.ndarray:
    """Conductances from the readings by the fixed-point iteration (converges when each column's
    readings sum below the drive voltage, which any physical matrix satisfies)."""
    if closed_form_start:
        s = np.minimum(v.sum(axis=0, keepdims=True) / v_drive, 1 - 1e-12)
        G = v * (g_ref + g_ref * s / (1 - s)) / v_drive
    else:
        G = v * g_ref / v_drive
    for _ in range(iterations):
        new = v * (g_ref + G.sum(axis=0, keepdims=True)) / v_drive
        if np.max(np.abs(new - G)) <= tol * max(1.0, float(np.max(np.abs(new)))):
            return new
        G = new
    return G


def network_readings(G: np.ndarray, g_ref: float, v_drive: float = 1.0) -> np.ndarray:
    """Forward model by nodal analysis: for each driven excitation line, Kirchhoff's current law at
    every reception node (cells to all excitation lines, R_ref to ground), solved as a linear system."""
    rows, cols = G.shape
    out = np.empty_like(G, dtype=float)
    for i in range(rows):
        e = np.zeros(rows)
        e[i] = v_drive  # the driven line; the others held at ground
        # Node j: sum_k G_kj (e_k - v_j) = g_ref v_j -> (g_ref + sum_k G_kj) v_j = sum_k G_kj e_k
        A = np.diag(g_ref + G.sum(axis=0))
        out[i] = np.linalg.solve(A, G.T @ e)
    return out


def direct(v: np.ndarray, g_ref: float, v_drive: float = 1.0) -> np.ndarray:
    """Exact inverse by one 16x16 linear solve per reception line:
    (V I - v_j 1^T) G_j = g_ref v_j for column j."""
    rows, cols = v.shape
    G = np.empty_like(v, dtype=float)
    for j in range(cols):
        A = v_drive * np.eye(rows) - np.outer(v[:, j], np.ones(rows))
        G[:, j] = np.linalg.solve(A, g_ref * v[:, j])
    return G
