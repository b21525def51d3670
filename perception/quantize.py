"""``xm detector quantize``: int8 copies of the detector's ONNX graphs for ONNX Runtime.

Each stage's graph (model.onnx, hands.onnx, objects.onnx) gets a sibling ``<stem>.int8.onnx``:
weights int8 per output channel, activations uint8 with ranges calibrated on un-augmented samples
of the labelled set (the stage's own training sampler), in ONNX's QDQ format, which ONNX Runtime
runs with integer kernels (VNNI where the CPU has it). The heatmap head stays float: the sub-pixel
peak reads the logarithm of three neighbouring heatmap values, which 8-bit steps would coarsen.
Each int8 graph records the SHA-256 of the float graph it came from, so recon never pairs it with
retrained weights (services/recon/onnx_graphs.py runs the float graph then).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from perception.augment import NO_AUGMENT
from perception.train import Sampler, load_set, window_sampler
from services.recon.learned_detector import DEFAULT_WEIGHTS_DIR, HAND_INPUT, OBJECT_INPUT, TRAINING_DIR
from services.recon.onnx_graphs import SOURCE_KEY, file_sha256, int8_path

HEAD = "/head/Conv"  # the U-Net's 1x1 heatmap convolution, kept float
STAGES = ("model", "hands", "objects")  # graph stems: first stage, hand stage, object stage


def quantize_graph(float_graph: Path, inputs: list[np.ndarray], out: Path | None = None) -> Path:
    """Writes the int8 copy of ``float_graph`` calibrated on ``inputs`` (each (1, 3, h, w) float32)."""
    import onnx  # the graph's format: reading and tagging it
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    if not inputs:
        raise ValueError(f"{float_graph}: no calibration inputs")

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.items = iter(inputs)

        def get_next(self) -> dict | None:
            x = next(self.items, None)
            return None if x is None else {"image": np.ascontiguousarray(x, np.float32)}

    out = Path(out) if out is not None else int8_path(float_graph)
    heads = [n.name for n in onnx.load(str(float_graph)).graph.node if n.name == HEAD]
    with tempfile.TemporaryDirectory() as tmp:  # the calibrator's scratch graphs
        staged = Path(tmp) / out.name
        quantize_static(str(float_graph), str(staged), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax, nodes_to_exclude=heads)
        model = onnx.load(str(staged))
    onnx.helper.set_model_props(model, {SOURCE_KEY: file_sha256(float_graph)})
    onnx.save(model, str(out))
    return out


def stage_samplers(task: str, frames: list, images: list, first_size: tuple[int, int]) -> dict[str, Sampler]:
    """Per graph stem, its training sampler without augmentation."""
    from perception import hand_stage, object_stage

    return {"model": window_sampler(frames, images, first_size, NO_AUGMENT),
            "hands": hand_stage.crop_sampler(frames, images, HAND_INPUT, NO_AUGMENT),
            "objects": object_stage.crop_sampler(frames, images, task, OBJECT_INPUT, NO_AUGMENT)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="xm detector quantize", description=__doc__.splitlines()[0])
    p.add_argument("--weights", default=str(DEFAULT_WEIGHTS_DIR),
                   help="folder of the float graphs; the int8 ones are written beside them")
    p.add_argument("--labels", default=str(TRAINING_DIR / "labels" / "train"),
                   help="labelled set the calibration samples come from (`xm detector label` writes one)")
    p.add_argument("--samples", type=int, default=150, help="calibration inputs per stage")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    folder, labels = Path(a.weights), Path(a.labels)
    if not (labels / "labels.json").exists():
        print(f"no labelled set at {labels}; make one with `xm detector label`")
        return 2
    graphs = [folder / f"{stem}.onnx" for stem in STAGES if (folder / f"{stem}.onnx").exists()]
    if not graphs:
        print(f"no detector graphs (model.onnx, hands.onnx, objects.onnx) in {folder}; `make detector` trains them")
        return 2
    size = tuple(json.loads((folder / "meta.json").read_text())["input_size"])
    task, frames, images = load_set(labels)
    samplers = stage_samplers(task, frames, images, size)
    for graph in graphs:
        rng = np.random.default_rng(a.seed)
        inputs = [samplers[graph.stem](rng)[0][None] for _ in range(a.samples)]
        out = quantize_graph(graph, inputs)
        print(f"{graph.name}: {a.samples} calibration inputs from {labels} -> {out} "
              f"({out.stat().st_size / 1e6:.1f} MB of {graph.stat().st_size / 1e6:.1f})")
    return 0
