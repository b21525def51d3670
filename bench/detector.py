"""The learned keypoint detector's inference time per 7-camera frame set (thesis 5.6, P6 budget:
detection + reconstruction <= 50 ms median on 2 cores), through five CPU runtimes: torch eager
(the baseline), TorchScript (traced and frozen), torch.compile (inductor), ONNX Runtime and ONNX
Runtime on the int8 graph (perception/quantize.py).

A frame set is the first seven window images of the held-out labelled set (``xm detector label``),
or, without one, seven 80x72 windows of noise; the timed call is the whole ``detect``: letterbox,
network, sub-pixel peaks, mapping to full-image pixels. Weights from runs/detector when trained,
else random ones (inference time does not depend on their values). Medians of wall time with
``--threads`` intra-op threads, ratios against eager measured in the same run. The machine is
shared: figures are noisy. Writes ``speed`` into .bench/detector.json, and ``graphs``: each
graph of the shipped detector alone, float and int8, on one frame set's batch.
"""

from __future__ import annotations

import argparse
import atexit
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

import torch  # noqa: E402

from perception.labels import keypoint_names  # noqa: E402
from perception.train import load_set, save  # noqa: E402
from services.recon.detector import CameraModel  # noqa: E402
from services.recon.learned_detector import (  # noqa: E402
    DEFAULT_WEIGHTS_DIR,
    INPUT_SIZE,
    TRAINING_DIR,
    LearnedDetector,
    UNet,
    View,
)


def frame_set(labels: Path) -> list[View]:
    if (labels / "labels.json").exists():
        _, frames, images = load_set(labels)
        return [View(fr.camera, CameraModel(np.zeros((3, 4)), *fr.full_size, tuple(fr.roi)), img)
                for fr, img in list(zip(frames, images, strict=True))[:7]]
    rng = np.random.default_rng(0)
    return [View(f"cam{i}", CameraModel(np.zeros((3, 4)), 256, 192, (80, 60, 80, 72)),
                 rng.integers(0, 256, (72, 80, 3), np.uint8)) for i in range(7)]


def time_calls(call, repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` calls, after one warm-up call (allocations, first-call graph work)."""
    call()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        out.append(time.perf_counter() - t0)
    return out


def runtimes(folder: Path, threads: int, compile_too: bool, views: list[View]) -> dict:
    """name -> a function making a detector whose ``heatmaps`` runs through that runtime; each is
    made just before it is timed, so no runtime's threads or compile workers idle beside another's."""
    def scripted() -> LearnedDetector:
        det = LearnedDetector(folder, runtime="torch")
        example = torch.zeros(7, 3, det.size[1], det.size[0])
        with torch.inference_mode():
            graph = torch.jit.freeze(torch.jit.trace(first_stage(folder, det), example).eval())
        det.heatmaps = lambda b: _run(graph, b)
        return det

    def compiled() -> LearnedDetector:
        det = LearnedDetector(folder, runtime="torch")
        net = torch.compile(first_stage(folder, det), dynamic=False)
        det.heatmaps = lambda b: _run(net, b)
        return det

    out = {"torch eager": lambda: LearnedDetector(folder, runtime="torch"), "torchscript (frozen)": scripted}
    if compile_too:
        out["torch.compile"] = compiled
    if (folder / "model.onnx").exists():
        out["onnxruntime"] = lambda: LearnedDetector(folder, runtime="onnx", threads=threads)
        out["onnxruntime int8"] = lambda: LearnedDetector(int8_copy(folder, views), runtime="onnx", threads=threads,
                                                          precision="int8")
    return out


def int8_copy(folder: Path, views: list[View]) -> Path:
    """A temporary copy of ``folder`` whose first stage also has its int8 graph (perception/quantize.py),
    calibrated on the timed windows: the int8 row's speed, not its accuracy (bench/recon.py has that)."""
    from perception.quantize import quantize_graph
    from services.recon.learned_detector import to_input

    copy = Path(tempfile.mkdtemp(prefix="detector-int8-"))
    atexit.register(shutil.rmtree, copy, True)
    for f in folder.iterdir():
        if f.suffix in (".json", ".onnx") and not f.name.endswith(".int8.onnx"):
            shutil.copy(f, copy / f.name)
    size = tuple(json.loads((folder / "meta.json").read_text())["input_size"])
    batch, _ = to_input([v.image for v in views], size)
    quantize_graph(copy / "model.onnx", [b[None] for b in batch])
    return copy


def time_graphs(folder: Path, threads: int, repeats: int) -> dict:
    """Each shipped graph alone, float and int8, on one frame set's batch (7 windows, 14 hand crops,
    8 object crops: what recon runs per frame set); medians of wall time in ms."""
    from services.recon.onnx_graphs import onnx_runner

    sizes = {"model": ("meta.json", 7), "hands": ("hands.json", 14), "objects": ("objects.json", 8)}
    rows = {}
    for stem, (meta, batch) in sizes.items():
        if not (folder / f"{stem}.onnx").exists() or not (folder / meta).exists():
            continue
        size = json.loads((folder / meta).read_text())["input_size"]
        w, h = (size, size) if isinstance(size, int) else size
        x = np.random.default_rng(0).random((batch, 3, h, w), dtype=np.float32)
        row = {"batch": batch}
        for precision in ("float32", "int8"):
            try:
                run, _ = onnx_runner(folder / f"{stem}.onnx", threads, precision)
            except FileNotFoundError as exc:
                row[precision] = str(exc)
                continue
            t = time_calls(lambda run=run, x=x: run(x), repeats)
            row[f"{precision}_ms"] = round(1e3 * float(np.median(t)), 2)
        if "int8_ms" in row and "float32_ms" in row:
            row["speedup"] = round(row["float32_ms"] / row["int8_ms"], 2)
        rows[stem] = row
    return rows


def first_stage(folder: Path, det: LearnedDetector) -> UNet:
    net = UNet(len(det.names))
    net.load_state_dict(torch.load(folder / "weights.pt", map_location="cpu", weights_only=True))
    return net.eval()


def _run(fn, batch: np.ndarray) -> np.ndarray:
    with torch.inference_mode():
        return fn(torch.from_numpy(batch)).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", default=str(TRAINING_DIR), help="a training run's folder (weights.pt)")
    parser.add_argument("--labels", default=str(TRAINING_DIR / "labels" / "eval"))
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-compile", action="store_true", help="skip torch.compile (its compile takes minutes)")
    parser.add_argument("--graphs", default=str(DEFAULT_WEIGHTS_DIR),
                        help="also time each graph of this folder alone, float and int8 ('' to skip)")
    parser.add_argument("--out", default=".bench/detector.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    folder = Path(args.weights)
    trained = (folder / "weights.pt").exists() and (folder / "meta.json").exists()
    tmp = None
    if not trained:
        tmp = tempfile.TemporaryDirectory()
        folder = Path(tmp.name)
        names = keypoint_names("assembly")
        save(UNet(len(names)), "assembly", INPUT_SIZE, [], 0.0, folder, {})
    views = frame_set(Path(args.labels))
    rows = {}
    for name, make in runtimes(folder, args.threads, not args.no_compile, views).items():
        try:
            det = make()
            t = time_calls(lambda det=det: det.detect(views), args.repeats)
        except Exception as exc:  # torch.compile needs a C++ toolchain; a runtime that fails is reported, not fatal
            print(f"{name}: unavailable ({type(exc).__name__}: {str(exc)[:200]})")
            continue
        del det
        rows[name] = {"median_ms": round(1e3 * float(np.median(t)), 1),
                      "p90_ms": round(1e3 * float(np.quantile(t, 0.9)), 1)}
    base = rows["torch eager"]["median_ms"]
    for r in rows.values():
        r["speedup_vs_eager"] = round(base / r["median_ms"], 2)
    fastest = min(rows, key=lambda k: rows[k]["median_ms"])
    default = LearnedDetector(folder).runtime
    print(f"detect() on one frame set of {len(views)} windows (input {INPUT_SIZE[0]}x{INPUT_SIZE[1]}, "
          f"{args.threads} threads, {'trained' if trained else 'random'} weights); medians of {args.repeats}")
    print(f"{'runtime':>22} {'median ms':>10} {'p90 ms':>8} {'x eager':>8}")
    for name, r in rows.items():
        print(f"{name:>22} {r['median_ms']:>10} {r['p90_ms']:>8} {r['speedup_vs_eager']:>8}")
    print(f"fastest: {fastest}; LearnedDetector's default runtime here: {default}")
    graphs = time_graphs(Path(args.graphs), args.threads, args.repeats) if args.graphs else {}
    for stem, r in graphs.items():
        print(f"graph {stem} (batch {r['batch']}): float {r.get('float32_ms')} ms, int8 {r.get('int8_ms')} ms, "
              f"x{r.get('speedup')}")
    out = Path(args.out)
    doc = json.loads(out.read_text()) if out.exists() else {}
    if graphs:
        doc["graphs"] = {"folder": args.graphs, "threads": args.threads, "repeats": args.repeats, "stages": graphs}
    doc["speed"] = {"views": len(views), "input_size": list(INPUT_SIZE), "threads": args.threads,
                    "weights": "trained" if trained else "random", "repeats": args.repeats, "runtimes": rows,
                    "fastest": fastest, "default_runtime": default, "p6_budget_ms": 50.0}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {out}")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
