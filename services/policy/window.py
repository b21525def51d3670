"""The time-window observation of Table 7.1 row (4) (thesis 7.6.8): the policy's input extended from
the current sample to the last ``sum(blocks)`` samples, older ones averaged in blocks.

``blocks`` lists block lengths oldest first, e.g. (8, 4, 2, 1, 1): 16 samples, of which the last
block is the current sample itself (the network's ordinary inputs). The older blocks' means are the
extra inputs. Before an episode has that many samples, the window is padded with its first sample.
A block's mean counts as observed for a point only where every sample of the block observed it.

Training (``step_windows``) and the rollout (``block_means`` on the history it carries, and the
same arithmetic in compiled.py) build the window the same way.
"""

from __future__ import annotations

import numpy as np


class WindowError(ValueError):
    """Block lengths that do not describe a window ending at the current sample."""


def check_blocks(blocks: tuple[int, ...]) -> None:
    """() (no window) or positive lengths whose last block is the current sample alone."""
    if not blocks:
        return
    if any(int(b) != b or b < 1 for b in blocks):
        raise WindowError(f"window blocks {blocks}: lengths must be positive integers")
    if blocks[-1] != 1:
        raise WindowError(f"window blocks {blocks}: the last block must be the current sample (length 1)")
    if len(blocks) < 2:
        raise WindowError(f"window blocks {blocks}: a window needs at least one block before the current sample")


def history_length(blocks: tuple[int, ...]) -> int:
    """How many samples before the current one the window reads (0 without a window)."""
    return sum(blocks) - 1 if blocks else 0


def block_starts(blocks: tuple[int, ...]) -> np.ndarray:
    """Index of each older block's first sample in the history (oldest first), (len(blocks) - 1,)."""
    return np.concatenate([[0], np.cumsum(blocks[:-2])]).astype(np.int64) if len(blocks) > 1 else np.zeros(0, int)


def pad_history(first: np.ndarray, blocks: tuple[int, ...]) -> np.ndarray:
    """The history at an episode start: its first sample repeated, (history_length, *first.shape)."""
    return np.repeat(np.asarray(first)[None], history_length(blocks), axis=0)


def push_history(history: np.ndarray, current: np.ndarray) -> np.ndarray:
    """The history one step later: the oldest sample dropped, ``current`` appended."""
    if len(history) == 0:
        return history
    return np.concatenate([history[1:], np.asarray(current, history.dtype)[None]])


def block_means(history: np.ndarray, history_mask: np.ndarray, blocks: tuple[int, ...]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Means of the older blocks over a history (W-1, P, 3) with its masks (W-1, P), oldest first:
    positions (B-1, P, 3) and whether each block observed each point throughout (B-1, P)."""
    history, history_mask = np.asarray(history, float), np.asarray(history_mask, bool)
    if len(history) != history_length(blocks):
        raise WindowError(f"history of {len(history)} samples; the window {blocks} needs {history_length(blocks)}")
    means, seen = [], []
    for start, n in zip(block_starts(blocks), blocks[:-1], strict=True):
        means.append(history[start:start + n].mean(axis=0))
        seen.append(history_mask[start:start + n].all(axis=0))
    return np.array(means).reshape(-1, *history.shape[1:]), np.array(seen, bool).reshape(-1, *history.shape[1:2])


def step_windows(pos: np.ndarray, mask: np.ndarray, step_index: np.ndarray, blocks: tuple[int, ...]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The older blocks' means for every sample of concatenated episodes: pos (N, P, 3), mask (N, P),
    ``step_index`` (N,) each sample's index in its episode (consecutive within an episode).
    Returns positions (N, B-1, P, 3) and observed masks (N, B-1, P); samples before an episode's
    first are its first."""
    n = len(pos)
    i = np.arange(n)
    episode_start = i - np.asarray(step_index)
    back = history_length(blocks)
    means = np.empty((n, len(blocks) - 1, *pos.shape[1:]))
    seen = np.empty((n, len(blocks) - 1, *mask.shape[1:]), bool)
    for b, (start, length) in enumerate(zip(block_starts(blocks), blocks[:-1], strict=True)):
        # history index h is the sample i - back + h, clamped at the episode's first
        idx = np.maximum(i[:, None] - back + start + np.arange(length)[None], episode_start[:, None])
        means[:, b] = pos[idx].mean(axis=1)
        seen[:, b] = mask[idx].all(axis=1)
    return means, seen
