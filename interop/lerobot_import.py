"""``xm import lerobot``: a LeRobot dataset v3 directory written by ``xm export lerobot`` -> our
demonstrations (``shared.demo.Demo``, saved as ``.npz``), episode boundaries from the episode
table, keypoints and masks from ``observation.state`` / ``observation.state_mask``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from interop import lerobot_format as fmt
from shared.demo import Demo


def read_info(root: Path) -> dict:
    path = root / fmt.INFO_PATH
    if not path.exists():
        raise fmt.FormatError(f"{root}: no {fmt.INFO_PATH}; not a LeRobot v3 dataset")
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise fmt.FormatError(f"{path}: not JSON ({exc})") from None
    fmt.check_info(info)
    return info


def read_episodes(root: Path) -> list[dict]:
    files = sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    if not files:
        raise fmt.FormatError(f"{root}: no meta/episodes/chunk-*/file-*.parquet")
    rows = [r for f in files for r in pq.read_table(f).to_pylist()]
    return sorted(rows, key=lambda r: r["episode_index"])


def import_dataset(root: str | Path) -> list[Demo]:
    """Every episode of the dataset at ``root`` as a Demo (dt = 1 / fps)."""
    root = Path(root)
    info = read_info(root)
    feats = info["features"]
    object_names = fmt.object_names_of(list(feats["observation.state"]["names"]))
    keys = ["observation.state", "observation.state_mask", "observation.tactile", "observation.tactile_mask",
            "index"] + (["observation.phase"] if "observation.phase" in feats else [])
    tables: dict[str, dict[str, np.ndarray]] = {}
    demos = []
    for ep in read_episodes(root):
        path = info["data_path"].format(chunk_index=ep["data/chunk_index"], file_index=ep["data/file_index"])
        if path not in tables:
            if not (root / path).exists():
                raise fmt.FormatError(f"{root}: episode {ep['episode_index']} names {path}, which is missing")
            t = pq.read_table(root / path, columns=keys)
            tables[path] = {k: _numpy(t.column(k)) for k in keys}
        cols = tables[path]
        rows = np.flatnonzero((cols["index"] >= ep["dataset_from_index"]) & (cols["index"] < ep["dataset_to_index"]))
        if len(rows) != ep["length"]:
            raise fmt.FormatError(f"{root}: episode {ep['episode_index']} has {len(rows)} rows in {path}, "
                                  f"its length says {ep['length']}")
        meta = json.loads(ep["xm_meta"]) if ep.get("xm_meta") else {}
        meta |= {"episode_index": ep["episode_index"], "source": str(root)}
        if "task" not in meta and ep.get("tasks"):
            meta["task"] = ep["tasks"][0]
        demos.append(fmt.episode_to_demo({k: v[rows] for k, v in cols.items()}, object_names, info["fps"], meta))
    return demos


def _numpy(col) -> np.ndarray:
    """A Parquet column as an array: fixed-size or plain lists as (N, D), scalars as (N,)."""
    col = col.combine_chunks()
    if pa.types.is_fixed_size_list(col.type) or pa.types.is_list(col.type):
        flat = col.flatten().to_numpy(zero_copy_only=False)
        return flat.reshape(len(col), -1)
    return col.to_numpy(zero_copy_only=False)


def save_demos(demos: list[Demo], out: str | Path) -> list[Path]:
    """``out/episode_NNNNNN.npz`` per demonstration (``Demo.load`` reads them)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for d in demos:
        p = out / f"episode_{int(d.meta.get('episode_index', len(paths))):06d}.npz"
        d.save(p)
        paths.append(p)
    return paths
