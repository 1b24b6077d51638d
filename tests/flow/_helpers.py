"""Helpers of the flow tests (a uniquely named module: every test folder has a conftest)."""

import numpy as np


def write_image_folder(folder, frames, names=None):
    from clflow.media import write_image

    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"frame_{i}.png" for i in range(len(frames))]  # unpadded: order by number, not text
    for name, frame in zip(names, frames):
        write_image(folder / name, frame)
    return folder


def mean_abs(a, b):
    return float(np.abs(a.astype(np.int32) - b.astype(np.int32)).mean())
