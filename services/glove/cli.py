"""`xm glove calibrate RECORDING.mcap`: per-cell calibration from paired raw readings and forces;
`xm glove register NAME [VALUE]`: the readout module's registers through the running glove service.

Pairs each raw impedance frame of a glove (`xm/glove/<hand>/raw`) with the nearest reference
force (`xm/world/sim/truth` contact forces in the simulation; a force sensor's channel on the
bench) of the same hand, converts region forces to cell pressure, fits the rational model of
thesis 4.5.6 per cell and the linear model for comparison, and reports correlation and relative
non-linearity as in thesis 4.8.4.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader

from services.glove.calibration import Calibration, fit_linear, fit_rational, rational, report
from services.glove.layout import CELL_MASK, CELL_REGION, pressure_from_forces, region_means
from shared import msgs
from shared.client import add_connection_args, connect
from shared.demo import HAND_NAMES
from shared.protocols import tactile

TRUTH = "xm/world/sim/truth"


def load_pairs(path: Path, hand: str) -> tuple[np.ndarray, np.ndarray]:
    """(N,16,16) complex readings and (N,6) reference region forces of one hand."""
    raw_key = f"xm/glove/{hand}/raw"
    readings, forces = [], []
    with AnyReader([path], default_typestore=msgs.typestore()) as reader:
        topics = {c.topic for c in reader.connections}
        missing = [k for k in (raw_key, TRUTH) if k not in topics]
        if missing:
            raise ValueError(f"{path}: no messages on {missing} (enable publish_raw for the glove and record "
                             f"the reference forces)")
        conns = [c for c in reader.connections if c.topic in (raw_key, TRUTH)]
        for conn, _, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            t = msgs.stamp_seconds(m.header.stamp)
            if conn.topic == raw_key:
                readings.append((t, (np.asarray(m.real) + 1j * np.asarray(m.imag)).reshape(16, 16)))
            else:
                forces.append((t, np.asarray(m.contact_forces, float).reshape(len(HAND_NAMES), -1)[
                    HAND_NAMES.index(hand)]))
    if not readings or not forces:
        raise ValueError(f"{path}: no raw readings or no reference forces for the {hand} glove")
    ft = np.array([t for t, _ in forces])
    fv = np.array([f for _, f in forces])
    idx = np.clip(np.searchsorted(ft, [t for t, _ in readings]), 0, len(ft) - 1)
    return np.array([z for _, z in readings]), fv[idx]


def calibrate(readings: np.ndarray, forces: np.ndarray) -> tuple[Calibration, dict, dict]:
    pressure = np.array([pressure_from_forces(f) for f in forces])  # (N,16,16) reference kPa
    cap = readings.imag
    unloaded = pressure.reshape(len(pressure), -1).max(axis=1) < 1e-6
    if unloaded.sum() < 5:
        raise ValueError("need unloaded samples to find the baselines (record some time with no contact)")
    c0 = np.median(cap[unloaded], axis=0)
    a = np.full((16, 16), 0.02)
    b = np.zeros((16, 16))
    lin = np.zeros((16, 16))
    for r, c in zip(*np.nonzero(CELL_MASK), strict=True):
        p = pressure[:, r, c]
        if p.max() <= 0:
            continue
        rel = (cap[:, r, c] - c0[r, c]) / c0[r, c]
        a[r, c], b[r, c] = fit_rational(p, rel)
        lin[r, c] = fit_linear(p, rel)[0]
    cal = Calibration(c0, a, b)
    predicted = np.array([region_means(cal.pressure(z)) for z in readings])
    reference = np.array([region_means(p) for p in pressure])
    loaded = reference.max(axis=0) > 0
    safe_c0 = np.where(CELL_MASK == 1, c0, 1.0)  # unpopulated crossings read ~0: never divide by them
    rel = (cap - c0) / safe_c0 * CELL_MASK
    rel_region = np.array([region_means(r) for r in rel])
    rational_report = report(reference[:, loaded].ravel(), predicted[:, loaded].ravel(),
                             rel_region[:, loaded].ravel())
    lin_pred = np.array([region_means(np.where(lin > 0, r / np.maximum(lin, 1e-9), 0)) for r in rel])
    linear_report = report(reference[:, loaded].ravel(), lin_pred[:, loaded].ravel(), rel_region[:, loaded].ravel())
    return cal, rational_report, linear_report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm glove", description="Glove tools.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    cal = sub.add_parser("calibrate", help="fit the per-cell calibration from a recording")
    cal.add_argument("recording")
    cal.add_argument("--hand", default="left", choices=list(HAND_NAMES))
    cal.add_argument("-o", "--output", help="calibration JSON (default runs/calibration/glove-<hand>.json)")
    reg = sub.add_parser("register", help="read or write a register of a running glove's readout module",
                         description="Reads (no VALUE) or writes a configuration register of the readout module "
                                     "through the running glove service (names: docs/protocols/tactile.md), "
                                     "e.g. `xm glove register --hand left rx_enable 0x3f`.")
    reg.add_argument("name", help=f"register: {', '.join(tactile.REGISTER_NAMES.values())}")
    reg.add_argument("value", nargs="?", type=lambda v: int(v, 0), help="value to write (decimal or 0x...)")
    reg.add_argument("--hand", default="left", choices=list(HAND_NAMES))
    add_connection_args(reg)
    args = parser.parse_args(argv)
    if args.cmd == "register":
        return register_main(args)
    path = Path(args.recording)
    if not path.exists():
        print(f"error: {path} not found", file=sys.stderr)
        return 2
    try:
        readings, forces = load_pairs(path, args.hand)
        calibration, rat, lin = calibrate(readings, forces)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.output or f"runs/calibration/glove-{args.hand}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    calibration.save(out)
    out.with_suffix(".report.json").write_text(json.dumps({"rational": rat, "linear": lin}, indent=2))
    _plot(readings, forces, calibration, out.with_suffix(".png"))
    print(f"{len(readings)} paired frames; rational model: correlation {rat['correlation']:.4f}, relative "
          f"non-linearity {rat['relative_nonlinearity']:.3f}; linear model: correlation {lin['correlation']:.4f}")
    print(f"wrote {out}, {out.with_suffix('.report.json')} and {out.with_suffix('.png')}")
    return 0


def register_main(args: argparse.Namespace) -> int:
    session, _, _ = connect(args)
    if session is None:
        return 2
    try:
        request = {"name": args.name, **({"value": args.value} if args.value is not None else {})}
        replies = [json.loads(r.ok.payload.to_bytes()) for r in
                   session.get(f"xm/glove/{args.hand}/@cmd/register", payload=json.dumps(request), timeout=3.0)
                   if r.ok is not None]
    finally:
        session.close()
    if not replies:
        print(f"error: no glove service for the {args.hand} hand answered (is the workcell up?)", file=sys.stderr)
        return 2
    reply = replies[0]
    if not reply.get("ok"):
        print(f"error: {reply.get('error') or reply.get('status')}", file=sys.stderr)
        return 1
    print(f"{reply['name']} (0x{reply['address']:04x}) = {reply['value']} (0x{reply['value']:x})")
    return 0


def _plot(readings: np.ndarray, forces: np.ndarray, cal: Calibration, path: Path) -> None:
    import matplotlib  # optional heavy dependency, loaded only to draw the plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    region = int(np.argmax(forces.max(axis=0)))
    r, c = np.argwhere(CELL_REGION == region)[0]
    p = np.array([pressure_from_forces(f)[r, c] for f in forces])
    rel = (readings.imag[:, r, c] - cal.c0[r, c]) / cal.c0[r, c]
    grid = np.linspace(0, p.max(), 100)
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(p, rel, ".", ms=2, alpha=0.4, label="measured")
    ax.plot(grid, rational(grid, cal.a[r, c], cal.b[r, c]), "r", label="rational fit")
    ax.set_xlabel("reference pressure (kPa)")
    ax.set_ylabel("relative capacitance change")
    ax.set_title(f"cell ({r}, {c})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
