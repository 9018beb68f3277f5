"""RGB images of events and labels (NumPy only): the colours of ids, grey event images, label images.

Colours follow the field's conventions: images of events are drawn dark on white, clusters in fixed,
distinct colours that depend on the id alone (id ``k`` always gets the same colour, in every window),
unlabelled events in grey. Every function returns uint8 RGB arrays; :mod:`evseg_torch.viz.panels` lays
them out as the paper's Fig. 1 and :mod:`evseg_torch.viz.figures` shows them with matplotlib.
"""

from __future__ import annotations

import numpy as np

from evseg_torch.events.images import event_counts

# Okabe-Ito-like palette, readable for colour-blind viewers, for ids 0-9; higher ids step round the hue
# circle by the golden angle, so neighbouring ids differ.
PALETTE = np.array(
    [
        [0, 114, 178],
        [213, 94, 0],
        [0, 158, 115],
        [204, 121, 167],
        [230, 159, 0],
        [86, 180, 233],
        [240, 228, 66],
        [120, 60, 160],
        [140, 140, 140],
        [0, 0, 0],
    ],
    dtype=np.uint8,
)
UNLABELLED = np.array([190, 190, 190], dtype=np.uint8)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """RGB colour of each label (a cluster or object id), :math:`(N, 3)` uint8; negative labels are grey."""
    labels = np.asarray(labels, dtype=np.int64)
    colours = PALETTE[np.clip(labels, 0, len(PALETTE) - 1)]
    beyond = labels >= len(PALETTE)
    if np.any(beyond):
        hue = np.mod((labels[beyond] - len(PALETTE)) * 137.508, 360.0) / 60.0
        # Saturated, mid-bright colours (HSV with S = 0.75, V = 0.8), away from grey and white.
        high, low = 0.8 * 255, 0.2 * 255
        mid = low + (high - low) * (1 - np.abs(np.mod(hue, 2) - 1))
        sector = hue.astype(np.int64) % 6
        table = np.array([[0, 1, 2], [1, 0, 2], [2, 0, 1], [2, 1, 0], [1, 2, 0], [0, 2, 1]])[sector]
        values = np.stack([np.full_like(mid, high), mid, np.full_like(mid, low)], axis=1)
        colours[beyond] = np.rint(np.take_along_axis(values, table, axis=1)).astype(np.uint8)
    colours[labels < 0] = UNLABELLED
    return colours


def count_image(xy: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Events per pixel of rounded positions, :math:`(H, W)` float64; positions outside are dropped."""
    return event_counts(xy, sensor_size).astype(np.float64)


def render_event_image(xy: np.ndarray, sensor_size: tuple[int, int], saturation: float = 0.99) -> np.ndarray:
    """Grey image of events, dark where many events fall, :math:`(H, W, 3)` uint8."""
    counts = count_image(xy, sensor_size)
    top = np.quantile(counts[counts > 0], saturation) if np.any(counts > 0) else 1.0
    grey = 255 - np.clip(counts / max(top, 1e-9), 0, 1) * 255
    return np.repeat(grey.astype(np.uint8)[..., None], 3, axis=2)


def render_labels(xy: np.ndarray, labels: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Colour each pixel by the label most of its events carry, white where none fall, :math:`(H, W, 3)`."""
    shifted = np.asarray(labels, dtype=np.int64) + 1  # -1 (unlabelled) becomes 0
    votes = event_counts(xy, sensor_size, shifted, n_labels=int(shifted.max(initial=0)) + 1)
    image = label_colors(votes.argmax(axis=0) - 1)
    image[votes.sum(axis=0) == 0] = 255
    return image
