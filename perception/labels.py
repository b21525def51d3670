"""The labelled set on disk: COCO keypoints JSON beside PNG images, the format annotation tools
(CVAT, Label Studio, COCO Annotator) read and write, so hand-made labels and the simulator's
stand-in labels are interchangeable.

One COCO image is one camera's readout window. Each image carries, beyond COCO's fields, the
window (``roi``, full-image pixels) and the full image's size, so keypoints can be mapped back to
full-image pixels. One annotation per object instance (``left_hand``, ``right_hand`` and each
object of the task) holds ``[u, v, visibility]`` per keypoint in window pixels, pixel centres at
integer coordinates (OpenCV's convention), visibility as COCO defines it: 0 not labelled (outside
the window, behind the camera, or absent), 1 labelled but occluded, 2 visible. Pure: no rendering.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.world.teacher import OBJECT_POINTS
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND

HAND_KEYPOINTS = ("wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
                  *(f"{f}_{j}" for f in ("index", "middle", "ring", "little") for j in ("mcp", "pip", "dip", "tip")))
HAND_SKELETON = ((0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (7, 8), (0, 9), (9, 10), (10, 11),
                 (11, 12), (0, 13), (13, 14), (14, 15), (15, 16), (0, 17), (17, 18), (18, 19), (19, 20))
FORMAT = "coco-keypoints; pixel centres at integers; roi = window of the full image"


def categories(task: str) -> list[dict]:
    """COCO categories: the two hands (21 keypoints, MANO/OpenPose order), then the task's objects."""
    cats = [{"id": i + 1, "name": f"{h}_hand", "supercategory": "hand", "keypoints": list(HAND_KEYPOINTS),
             "skeleton": [[a + 1, b + 1] for a, b in HAND_SKELETON]} for i, h in enumerate(HAND_NAMES)]
    for obj, pts in OBJECT_POINTS[task].items():
        cats.append({"id": len(cats) + 1, "name": obj, "supercategory": "object", "keypoints": list(pts),
                     "skeleton": []})
    return cats


def keypoint_names(task: str) -> list[str]:
    """The detector's channels in recon's order: ``left/0..20``, ``right/0..20``, then the objects'
    keypoints as the world's truth lists them (``board/c0``, ...)."""
    names = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)]
    return names + [f"{obj}/{pt}" for obj, pts in OBJECT_POINTS[task].items() for pt in pts]


def keypoint_classes(task: str) -> np.ndarray:
    """Per channel: "hand" or "object"."""
    return np.array(["hand" if n.split("/")[0] in HAND_NAMES else "object" for n in keypoint_names(task)])


@dataclass
class Frame:
    """One labelled image: its file, the camera and window, and per channel uv (N,2) in window pixels
    with the visibility flag (N,) (0/1/2)."""
    file_name: str
    camera: str
    roi: tuple[int, int, int, int]
    full_size: tuple[int, int]
    uv: np.ndarray
    visibility: np.ndarray
    extra: dict = field(default_factory=dict)  # provenance: seed, demo, time


def write_coco(path: Path, task: str, frames: list[Frame], description: str) -> None:
    cats = categories(task)
    images, anns = [], []
    for i, fr in enumerate(frames):
        images.append({"id": i + 1, "file_name": fr.file_name, "width": int(fr.roi[2]), "height": int(fr.roi[3]),
                       "camera": fr.camera, "roi": [int(v) for v in fr.roi], "full_width": int(fr.full_size[0]),
                       "full_height": int(fr.full_size[1]), **fr.extra})
        start = 0
        for cat in cats:
            n = len(cat["keypoints"])
            uv, vis = fr.uv[start:start + n], fr.visibility[start:start + n]
            start += n
            if not vis.any():
                continue  # an instance with no labelled keypoint is not annotated (COCO practice)
            kp = np.zeros((n, 3))
            kp[:, :2] = np.where(vis[:, None] > 0, uv, 0.0)
            kp[:, 2] = vis
            labelled = uv[vis > 0]
            lo, hi = labelled.min(axis=0), labelled.max(axis=0)
            anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": cat["id"],
                         "keypoints": [round(float(v), 3) for v in kp.ravel()], "num_keypoints": int((vis > 0).sum()),
                         "bbox": [round(float(v), 2) for v in (*lo, *(hi - lo))], "iscrowd": 0,
                         "area": float(np.prod(np.maximum(hi - lo, 1.0)))})
    doc = {"info": {"description": description, "format": FORMAT, "task": task}, "images": images,
           "annotations": anns, "categories": cats}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1))


def read_coco(path: Path) -> tuple[str, list[Frame]]:
    """The task and frames of a COCO keypoints file written here or by an annotation tool (its
    categories must be the task's, by name; images without ``roi`` are full frames)."""
    doc = json.loads(Path(path).read_text())
    task = doc.get("info", {}).get("task")
    if task not in OBJECT_POINTS:
        raise ValueError(f"{path}: info.task must name a task ({', '.join(OBJECT_POINTS)}), got {task!r}")
    want = categories(task)
    by_name = {c["name"]: c for c in doc["categories"]}
    offsets, start = {}, 0
    for cat in want:
        got = by_name.get(cat["name"])
        if got is None or list(got["keypoints"]) != cat["keypoints"]:
            raise ValueError(f"{path}: category {cat['name']!r} missing or with other keypoints than "
                             f"{cat['keypoints']}")
        offsets[got["id"]] = start
        start += len(cat["keypoints"])
    frames, index = [], {}
    for img in doc["images"]:
        roi = tuple(img.get("roi", (0, 0, img["width"], img["height"])))
        full = (img.get("full_width", img["width"]), img.get("full_height", img["height"]))
        extra = {k: v for k, v in img.items() if k not in ("id", "file_name", "width", "height", "camera", "roi",
                                                             "full_width", "full_height")}
        index[img["id"]] = len(frames)
        frames.append(Frame(img["file_name"], img.get("camera", ""), roi, full, np.zeros((start, 2)),
                            np.zeros(start, np.uint8), extra))
    for ann in doc["annotations"]:
        fr = frames[index[ann["image_id"]]]
        kp = np.asarray(ann["keypoints"], float).reshape(-1, 3)
        s = offsets[ann["category_id"]]
        fr.uv[s:s + len(kp)] = kp[:, :2]
        fr.visibility[s:s + len(kp)] = kp[:, 2].astype(np.uint8)
    return task, frames
