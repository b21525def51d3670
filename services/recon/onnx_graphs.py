"""The detector's graphs in ONNX Runtime: each stage's float graph (``<stem>.onnx``, exported by
training) or its int8 copy (``<stem>.int8.onnx``, perception/quantize.py), which records the
SHA-256 of the float graph it was made from so it is never paired with retrained weights."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

PRECISIONS = ("auto", "int8", "float32")
SOURCE_KEY = "float_graph_sha256"  # an int8 graph's metadata: the float graph it was made from


class WeightsMissingError(FileNotFoundError):
    pass


def check_precision(precision: str) -> None:
    if precision not in PRECISIONS:
        raise ValueError(f"detector precision {precision!r}: choose one of {', '.join(PRECISIONS)}")


def int8_path(float_graph: Path) -> Path:
    """Where the int8 copy of ``float_graph`` lives: model.onnx -> model.int8.onnx."""
    return Path(float_graph).with_suffix(".int8.onnx")


def file_sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def has_onnxruntime() -> bool:
    try:
        import onnxruntime  # noqa: F401  (optional dependency probe)
    except ImportError:
        return False
    return True


def onnx_runner(graph: Path, threads: int, precision: str = "auto") -> tuple[Callable[[np.ndarray], np.ndarray], str]:
    """A function batch (B,3,h,w) float32 -> heatmaps (B,K,h,w) for the float graph ``graph`` or its
    int8 copy, and the precision it runs at in words (with the reason when not int8).
    ``precision``: "auto" takes the int8 copy when it was made from ``graph``; "int8" requires it
    (WeightsMissingError otherwise); "float32" never takes it."""
    check_precision(precision)
    int8 = int8_path(graph)
    if precision == "float32":
        return _runner(_session(graph, threads)), "float32"
    if not int8.exists():
        why = f"float32 (no {int8.name}; `xm detector quantize` writes it)"
    else:
        session = _session(int8, threads)
        if session.get_modelmeta().custom_metadata_map.get(SOURCE_KEY) == file_sha256(graph):
            return _runner(session), "int8"
        why = f"float32 ({int8.name} was made from other weights; run `xm detector quantize` again)"
    if precision == "int8":
        raise WeightsMissingError(f"{graph.parent}: {why}")
    return _runner(_session(graph, threads)), why


def _session(path: Path, threads: int):  # -> onnxruntime.InferenceSession (an optional import)
    import onnxruntime as ort  # optional fast runtime: only when the graph was exported

    opts = ort.SessionOptions()
    opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
    # Trained weights and activations hold denormal floats, which the CPU computes slowly.
    opts.add_session_config_entry("session.set_denormal_as_zero", "1")
    # Idle threads sleep rather than spin: recon shares two cores with the other services.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def _runner(session) -> Callable[[np.ndarray], np.ndarray]:
    return lambda batch: session.run(None, {"image": batch})[0]
