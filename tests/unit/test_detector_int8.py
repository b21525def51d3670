"""The detector's int8 graphs (perception/quantize.py, services/recon/onnx_graphs.py): written
beside the float graph, run by ONNX Runtime close to it, and never paired with other weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from perception import quantize  # noqa: E402
from perception.train import export_onnx  # noqa: E402
from services.recon.learned_detector import UNet  # noqa: E402
from services.recon.onnx_graphs import WeightsMissingError, int8_path, onnx_runner  # noqa: E402

SIZE = (16, 16)


def float_graph(path, seed: int):
    torch.manual_seed(seed)
    assert export_onnx(UNet(3).eval(), SIZE, path)
    return path


def inputs(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.random((1, 3, SIZE[1], SIZE[0]), dtype=np.float32) for _ in range(n)]


def test_the_int8_graph_is_written_beside_its_float_graph_and_runs_close_to_it(tmp_path):
    graph = float_graph(tmp_path / "model.onnx", 0)
    out = quantize.quantize_graph(graph, inputs(16))
    assert out == int8_path(graph) == tmp_path / "model.int8.onnx"
    assert out.stat().st_size < graph.stat().st_size / 2, "weights stored as 8-bit integers"
    run8, said8 = onnx_runner(graph, threads=1)
    run32, said32 = onnx_runner(graph, threads=1, precision="float32")
    assert (said8, said32) == ("int8", "float32")
    x = np.concatenate(inputs(4, seed=1))
    y8, y32 = run8(x), run32(x)
    assert y8.shape == y32.shape == (4, 3, SIZE[1], SIZE[0])
    spread = float(y32.max() - y32.min())
    assert np.abs(y8 - y32).max() < 0.1 * spread, "int8 heatmaps stay near the float ones"
    assert not np.array_equal(y8, y32), "the int8 graph really ran"


def test_an_int8_graph_made_from_other_weights_is_not_used(tmp_path):
    graph = float_graph(tmp_path / "model.onnx", 0)
    quantize.quantize_graph(graph, inputs(8))
    float_graph(graph, 1)  # retrained: the int8 copy is now stale
    _, said = onnx_runner(graph, threads=1)
    assert said.startswith("float32") and "other weights" in said and "xm detector quantize" in said
    with pytest.raises(WeightsMissingError, match="other weights"):
        onnx_runner(graph, threads=1, precision="int8")


def test_a_missing_int8_graph_falls_back_to_float_unless_required(tmp_path):
    graph = float_graph(tmp_path / "model.onnx", 0)
    run, said = onnx_runner(graph, threads=1)
    assert said.startswith("float32") and "model.int8.onnx" in said
    assert run(inputs(1)[0]).shape == (1, 3, SIZE[1], SIZE[0])
    with pytest.raises(WeightsMissingError, match="xm detector quantize"):
        onnx_runner(graph, threads=1, precision="int8")
    with pytest.raises(ValueError, match="choose one of auto, int8, float32"):
        onnx_runner(graph, threads=1, precision="fp16")


def test_quantize_says_how_to_make_a_labelled_set_when_there_is_none(tmp_path, capsys):
    assert quantize.main(["--weights", str(tmp_path), "--labels", str(tmp_path / "none")]) == 2
    assert "xm detector label" in capsys.readouterr().out
