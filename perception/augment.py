"""Training samples for the keypoint detector: a labelled window image turned into the network's
input with random scale, rotation and shift (one affine map that includes the letterbox of
services/recon/learned_detector.py), colour, blur, noise and synthetic occluders, plus the
Gaussian heatmap targets. Pure numpy/OpenCV."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.recon.hand_crops import crop_matrix


@dataclass(frozen=True)
class AugmentParams:
    scale: tuple[float, float] = (0.75, 1.3)
    rotation_deg: float = 25.0
    shift: float = 0.1  # of the input size
    gain: float = 0.25  # per-channel colour gain spread
    brightness: float = 0.15
    contrast: float = 0.3
    blur_p: float = 0.3
    noise_p: float = 0.5
    noise_sigma: float = 0.04
    occluder_p: float = 0.5


NO_AUGMENT = AugmentParams(scale=(1.0, 1.0), rotation_deg=0.0, shift=0.0, gain=0.0, brightness=0.0, contrast=0.0,
                           blur_p=0.0, noise_p=0.0, occluder_p=0.0)


def letterbox_matrix(w: int, h: int, size: tuple[int, int]) -> np.ndarray:
    """2x3 affine map from window pixels to network pixels (pixel centres at integers): the same
    scale-to-fit and top-left placement as learned_detector.to_input."""
    s = min(size[0] / w, size[1] / h)
    return np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5]])


def random_matrix(w: int, h: int, size: tuple[int, int], p: AugmentParams, rng: np.random.Generator) -> np.ndarray:
    L = np.vstack([letterbox_matrix(w, h, size), [0, 0, 1]])
    s = min(size[0] / w, size[1] / h)
    centre = np.array([(w * s - 1) / 2, (h * s - 1) / 2])  # the content's centre in network pixels
    angle = rng.uniform(-p.rotation_deg, p.rotation_deg)
    zoom = rng.uniform(*p.scale)
    R = np.vstack([cv2.getRotationMatrix2D(tuple(centre), angle, zoom), [0, 0, 1]])
    shift = rng.uniform(-p.shift, p.shift, 2) * size
    T = np.array([[1, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1.0]])
    return (T @ R @ L)[:2]


def heatmaps(uv: np.ndarray, labelled: np.ndarray, size: tuple[int, int], sigma: float) -> np.ndarray:
    """(N, h, w) Gaussians of peak 1 at the labelled keypoints uv (N, 2) in network pixels."""
    w, h = size
    xs, ys = np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)
    gx = np.exp(-((xs[None, :] - uv[:, :1]) ** 2) / (2 * sigma**2))
    gy = np.exp(-((ys[None, :] - uv[:, 1:]) ** 2) / (2 * sigma**2))
    out = gy[:, :, None] * gx[:, None, :]
    return (out * labelled[:, None, None]).astype(np.float32)


def colour(img: np.ndarray, p: AugmentParams, rng: np.random.Generator) -> np.ndarray:
    x = img * rng.uniform(1 - p.gain, 1 + p.gain, 3)[None, None, :]
    mean = x.mean()
    x = (x - mean) * rng.uniform(1 - p.contrast, 1 + p.contrast) + mean + rng.uniform(-p.brightness, p.brightness)
    if rng.random() < p.blur_p:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.5, 1.3))
    if rng.random() < p.noise_p:
        x = x + rng.normal(0.0, rng.uniform(0.0, p.noise_sigma), x.shape)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def occluders(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One to three filled rectangles or ellipses of random colour, 10-35 % of the input's side."""
    h, w = img.shape[:2]
    out = img.copy()
    for _ in range(rng.integers(1, 4)):
        cw, ch = (rng.uniform(0.1, 0.35, 2) * [w, h]).astype(int) + 2
        x, y = rng.integers(0, w), rng.integers(0, h)
        col = tuple(float(c) for c in rng.uniform(0, 1, 3))
        if rng.random() < 0.5:
            cv2.rectangle(out, (int(x - cw // 2), int(y - ch // 2)), (int(x + cw // 2), int(y + ch // 2)), col, -1)
        else:
            angle = float(rng.uniform(0, 180))
            cv2.ellipse(out, (int(x), int(y)), (int(cw // 2), int(ch // 2)), angle, 0, 360, col, -1)
    return out


def sample(image: np.ndarray, uv: np.ndarray, visibility: np.ndarray, size: tuple[int, int], sigma: float,
           p: AugmentParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One training pair: input (3, h, w) float in [0, 1] and targets (N, h, w)."""
    h0, w0 = image.shape[:2]
    M = random_matrix(w0, h0, size, p, rng)
    warped = cv2.warpAffine(image.astype(np.float32) / 255.0, M, size, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    warped = colour(warped, p, rng)
    if rng.random() < p.occluder_p:
        warped = occluders(warped, rng)
    net_uv = uv @ M[:, :2].T + M[:, 2]
    inside = (net_uv[:, 0] >= -0.5) & (net_uv[:, 0] <= size[0] - 0.5) & (net_uv[:, 1] >= -0.5) & \
             (net_uv[:, 1] <= size[1] - 0.5)
    target = heatmaps(net_uv, ((visibility > 0) & inside).astype(np.float32), size, sigma)
    return warped.transpose(2, 0, 1), target


def augmented_crop(image: np.ndarray, uv: np.ndarray, labelled: np.ndarray, centre: np.ndarray, half: float,
                   size: int, mirror: bool, aug: AugmentParams, sigma: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A training pair from one window: the square ``half`` pixels around ``centre`` (mirrored if
    asked), rotated, recoloured and occluded as ``aug`` says, as the network's (3, size, size)
    input, and heatmaps of the ``labelled`` keypoints ``uv`` (window pixels) that land inside."""
    M = np.vstack([crop_matrix(centre, half, size, mirror), [0, 0, 1]])
    c = (size - 1) / 2.0
    R = np.vstack([cv2.getRotationMatrix2D((c, c), rng.uniform(-aug.rotation_deg, aug.rotation_deg), 1.0), [0, 0, 1]])
    A = (R @ M)[:2]
    warped = cv2.warpAffine(image.astype(np.float32) / 255.0, A, (size, size), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    warped = colour(warped, aug, rng)
    if rng.random() < aug.occluder_p:
        warped = occluders(warped, rng)
    net_uv = uv @ A[:, :2].T + A[:, 2]
    inside = np.all((net_uv >= -0.5) & (net_uv <= size - 0.5), axis=1)
    return warped.transpose(2, 0, 1), heatmaps(net_uv, (labelled & inside).astype(np.float32), (size, size), sigma)
