"""A guidance video registered to its first frame's camera and exposure over the static
pixels, before its optical flow: what a hand-held or generated video's drifting camera and
flickering exposure add to the flow, taken out.

    static = ~grown_object_mask                                # bool [H, W]
    frames, stabilisation = stabilise(video.frames, static)    # [T, H, W, 3] uint8
    stabilisation.record()                                     # for metrics.json

The static pixels (the scene outside the objects) should neither move nor change brightness.
For each frame t >= 1 corners of frame 0's static part are tracked into frame t, starting
where the frame before's warp puts them (a drifting camera's frame t is far from frame 0 but
near its predecessor), by pyramidal Lucas-Kanade (frame t's levels first fitted to frame
0's over them), both ways; the points whose round trip misses by over 0.5 px are dropped, and a
similarity (rotation, scale, translation) from frame t to frame 0 is fitted to the rest by
least median of squares; frame t is warped by it. Then each channel's gain and offset to
frame 0 are fitted over the registered static pixels (least squares on both frames a little
smoothed, again without the outliers) and applied. A correction smaller than what it could
resolve (a warp moving no pixel by MOTION_FLOOR_PX, an exposure changing no grey level by
EXPOSURE_FLOOR) is not applied, so a steady, evenly lit video, a rendering among them,
comes back the same bits. Without MIN_FEATURES trackable corners in the static part (a
plain backdrop) the camera is left alone and the record says so: a flat background shows
no camera motion, and none can be removed; a frame into which too few corners track is left
as it is, and named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clflow.errors import InputError

#: a warp that moves no pixel of the frame by more than this (px) is not applied
MOTION_FLOOR_PX = 0.1
#: an exposure correction that changes no grey level by more than this is not applied
EXPOSURE_FLOOR = 0.5
#: fewest tracked static corners that fit a camera motion: twice the similarity's 4 degrees
#: of freedom (the quick demo's 96 px guidance keeps 11 into its last frame under a 4 px drift)
MIN_FEATURES = 8
#: fewest static pixels that fit an exposure
MIN_STATIC_PIXELS = 400
#: the exposure is fitted on both frames under a Gaussian of this standard deviation (px):
#: JPEG's blocks and the warp's interpolation average out (on the quick torus under the
#: realistic degradation the fitted levels came closest to the truth's at 1 px: docs/flow.md)
EXPOSURE_SMOOTHING_PX = 1.0


@dataclass(frozen=True)
class Stabilisation:
    """What :func:`stabilise` removed from each of a video's T frames.

    warps: [T, 2, 3] the similarity taking frame t's pixels to frame 0's (identity where not
        applied); motion_px: [T] the farthest a pixel of frame t was moved (0 where not);
    gains, offsets: [T, C] each channel's exposure correction (frame 0's level = gain x
        frame t's + offset; 1 and 0 where not applied);
    features: [T] static corners the warp was fitted to (0 for frame 0); note: why the
        camera motion was left alone, or ""."""

    warps: np.ndarray
    motion_px: np.ndarray
    gains: np.ndarray
    offsets: np.ndarray
    features: np.ndarray
    note: str = ""

    def record(self) -> dict:
        """The summary for metrics.json: the largest and mean motion removed (px), the
        largest exposure change (grey levels at mid-grey), the frames changed, the note."""
        mid = np.abs(self.gains * 127.5 + self.offsets - 127.5)
        changed = (self.motion_px > 0) | (mid.max(axis=1) > 0)
        return {
            "motion_removed_px": {"max": float(self.motion_px.max()), "mean": float(self.motion_px[1:].mean())},
            "exposure_removed_grey_levels": float(mid.max()),
            "frames_changed": int(changed.sum()),
            "frames": len(self.motion_px),
            "min_features": int(self.features[1:].min()) if len(self.features) > 1 else 0,
            "note": self.note,
        }


def _grey(frame: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY) if frame.ndim == 3 else frame


def _matched(grey: np.ndarray, reference: np.ndarray, static: np.ndarray) -> np.ndarray:
    """``grey`` [H, W] uint8 with its static pixels' levels fitted to ``reference``'s
    (:func:`exposure_fit`; tracking then sees the same brightness in both), or ``grey``
    itself where the fit changes nothing."""
    gain, offset = exposure_fit(grey.astype(np.float64), reference.astype(np.float64), static)
    if (gain, offset) == (1.0, 0.0):
        return grey
    return np.clip(gain * grey + offset + 0.5, 0, 255).astype(np.uint8)


def _smooth(levels: np.ndarray) -> np.ndarray:
    """[H, W] float grey levels under a Gaussian of EXPOSURE_SMOOTHING_PX."""
    import cv2

    return cv2.GaussianBlur(levels, (0, 0), EXPOSURE_SMOOTHING_PX, borderType=cv2.BORDER_REFLECT101)


def _warped(image: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """``image`` [H, W(, C)] moved by the affine ``warp`` [2, 3] (bicubic, the border
    replicated); ``image`` itself for the identity."""
    import cv2

    if (warp == np.eye(2, 3)).all():
        return image
    height, width = image.shape[:2]
    return cv2.warpAffine(image, warp, (width, height), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def _displacement(warp: np.ndarray, width: int, height: int) -> float:
    """The farthest (px) ``warp`` [2, 3] moves a pixel of a width x height frame (at a corner)."""
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
    moved = corners @ warp[:, :2].T + warp[:, 2]
    return float(np.linalg.norm(moved - corners, axis=1).max())


def camera_warp(
    frame: np.ndarray, first: np.ndarray, static: np.ndarray, corners: np.ndarray, guess: np.ndarray
) -> tuple[np.ndarray | None, int]:
    """The similarity [2, 3] taking ``frame``'s pixels to ``first``'s (grey [H, W] uint8),
    fitted to the static ``corners`` [n, 1, 2] float32 of ``first`` tracked into ``frame``
    from where ``guess`` [2, 3] (a warp from ``frame`` to ``first``: the frame before's)
    puts them; None when fewer than MIN_FEATURES track both ways. Also the corners it was
    fitted to."""
    import cv2

    lk = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.01))
    matched = _matched(frame, first, static)
    inverse = cv2.invertAffineTransform(guess)
    start = (corners @ inverse[:, :2].T + inverse[:, 2]).astype(np.float32)
    ahead, ok_ahead, _ = cv2.calcOpticalFlowPyrLK(
        first, matched, corners, start, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
    )
    back, ok_back, _ = cv2.calcOpticalFlowPyrLK(
        matched, first, ahead, corners.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
    )
    good = (ok_ahead[:, 0] == 1) & (ok_back[:, 0] == 1) & (np.linalg.norm((back - corners)[:, 0], axis=1) < 0.5)
    if good.sum() < MIN_FEATURES:
        return None, int(good.sum())
    warp, inliers = cv2.estimateAffinePartial2D(
        ahead[good], corners[good], method=cv2.LMEDS, maxIters=4000, confidence=0.999
    )
    if warp is None or int(inliers.sum()) < MIN_FEATURES:
        return None, 0 if inliers is None else int(inliers.sum())
    return warp, int(inliers.sum())


def exposure_fit(frame: np.ndarray, first: np.ndarray, static: np.ndarray) -> tuple[float, float]:
    """(gain, offset) with ``first`` ~ gain x ``frame`` + offset over the ``static`` pixels
    of one channel (float [H, W]), neither end of the 8-bit range: least squares over the
    pixels whose change is within 3 robust spreads of the median change, then again over
    those within 3 robust spreads of that fit (a moving part that left the mask is neither)."""
    use = static & (frame > 2) & (frame < 253) & (first > 2) & (first < 253)
    x, y = frame[use].astype(np.float64), first[use].astype(np.float64)
    if x.size < MIN_STATIC_PIXELS or x.std() < 1.0:
        return 1.0, 0.0
    # the start: the pixels whose change is near the typical change (a gain moves levels
    # apart by a few grey levels; a moving part that left the mask, or passed through, by more)
    change = y - x
    keep = np.abs(change - np.median(change)) <= 3 * 1.4826 * np.median(np.abs(change - np.median(change))) + 1.0
    for _ in range(2):
        if keep.sum() < MIN_STATIC_PIXELS:
            return 1.0, 0.0
        gain, offset = np.polyfit(x[keep], y[keep], 1)
        residual = y - (gain * x + offset)
        spread = 1.4826 * np.median(np.abs(residual[keep] - np.median(residual[keep])))
        keep = np.abs(residual) <= 3 * spread + 1.0
    return float(gain), float(offset)


def stabilise(frames: np.ndarray, static: np.ndarray) -> tuple[np.ndarray, Stabilisation]:
    """``frames`` [T, H, W(, 3)] uint8 registered to frame 0's camera and exposure over the
    ``static`` [H, W] bool pixels (module docstring); the frames (a new array, or ``frames``
    itself when nothing was applied) and what was removed."""
    import cv2

    frames = np.asarray(frames)
    if frames.dtype != np.uint8 or frames.ndim not in (3, 4) or len(frames) < 2:
        raise InputError(
            f"stabilise: frames must be [T, H, W(, 3)] uint8 with T >= 2, got {frames.dtype} {frames.shape}"
        )
    static = np.asarray(static, bool)
    if static.shape != frames.shape[1:3]:
        raise InputError(f"stabilise: the static mask is {static.shape}, the frames {frames.shape[1:3]}")
    count, height, width = len(frames), frames.shape[1], frames.shape[2]
    channels = frames.shape[3] if frames.ndim == 4 else 1
    warps = np.repeat(np.eye(2, 3)[None], count, axis=0)
    motion = np.zeros(count)
    gains, offsets = np.ones((count, channels)), np.zeros((count, channels))
    features = np.zeros(count, int)
    note = ""
    greys = [_grey(f) for f in frames]
    reference = np.stack(
        [_smooth(c) for c in np.moveaxis(frames[0].astype(np.float64).reshape(height, width, channels), -1, 0)], -1
    )
    inner = cv2.erode(static.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0  # corners off the mask's edge
    corners = cv2.goodFeaturesToTrack(greys[0], 400, 0.005, 3, mask=inner.astype(np.uint8) * 255, blockSize=5)
    if corners is None or len(corners) < MIN_FEATURES:
        note = f"the camera's motion is not removed: {0 if corners is None else len(corners)} static corners to track, {MIN_FEATURES} needed"
    out = frames.copy()
    changed = False
    known = np.eye(2, 3)  # the latest frame's warp: where frame t's search starts (the camera drifts)
    lost = []  # frames whose camera could not be tracked: left as they are
    for t in range(1, count):
        frame, seen = frames[t], static
        if not note:
            warp, features[t] = camera_warp(greys[t], greys[0], static, corners.astype(np.float32), known)
            if warp is None:
                lost.append(t)
                continue
            known = warp
            moved = _displacement(warp, width, height)
            if moved > MOTION_FLOOR_PX:
                warps[t], motion[t] = warp, moved
                frame = _warped(frame, warp)
                margin = int(np.ceil(moved)) + 2  # the replicated border is no evidence of exposure
                seen = static.copy()
                seen[:margin], seen[-margin:], seen[:, :margin], seen[:, -margin:] = False, False, False, False
        levels = frame.astype(np.float64).reshape(height, width, channels)
        corrected = levels.copy()
        for c in range(channels):
            # fitted on both frames smoothed alike: the warp's interpolation softens frame t
            # alone, which would tilt the fit towards a higher gain
            gain, offset = exposure_fit(_smooth(levels[..., c]), reference[..., c], seen)
            if max(abs(offset), abs(255 * gain + offset - 255)) > EXPOSURE_FLOOR:
                gains[t, c], offsets[t, c] = gain, offset
                # a clipped level stays clipped: the sensor's white (a bright sky) was at
                # least that bright in frame 0 too, and its black as dark
                channel = levels[..., c]
                corrected[..., c] = np.where((channel <= 0) | (channel >= 255), channel, gain * channel + offset)
        if motion[t] > 0 or (gains[t] != 1).any() or (offsets[t] != 0).any():
            out[t] = np.clip(corrected + 0.5, 0, 255).astype(np.uint8).reshape(frames.shape[1:])
            changed = True
    if lost:
        note = f"frames {', '.join(map(str, lost))} are left as they are: under {MIN_FEATURES} static corners tracked into them"
    return (out if changed else frames), Stabilisation(warps, motion, gains, offsets, features, note)


__all__ = [
    "EXPOSURE_FLOOR",
    "MIN_FEATURES",
    "MOTION_FLOOR_PX",
    "Stabilisation",
    "camera_warp",
    "exposure_fit",
    "stabilise",
]
