"""What a generated or hand-held guidance video adds to a clean rendering, made reproducibly
for the benchmark (``clflow eval sysid --degrade``): exposure flicker, a shaking camera,
blur, JPEG compression and a playback speed other than real time. Sensor noise and a lossy
video codec are the benchmark's ``--noise`` and ``--codec``.

    frames = Degradation.parse("realistic").apply(frames, 96, np.random.default_rng(0))

Each frame is changed in the order a camera and an encoder would: the camera's shake (at the
rendering's resolution), the downsampling to the guidance size, blur, exposure, then
quantisation to 8 bits and JPEG. The shake is a random walk (frame 0 where the camera was
placed, each later frame moved from the one before by draws of ``shake`` px along each image
axis and ``roll`` deg about the image centre), so the camera drifts as a hand-held one does;
the exposure's gain and offset are drawn for each frame anew, as a flickering light or an
auto-exposure does. The playback speed is the case maker's (clflow_datasets.synthetic
.make_case): the ground truth is simulated at ``speed`` times the video's frame interval, the
video still labelled with the optimiser's frame rate.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

#: each artefact's allowed range (inclusive) and its unit, for the parser's messages
LIMITS = {
    "flicker": (0.0, 0.5, "relative gain's standard deviation"),
    "offset": (0.0, 64.0, "8-bit grey levels' standard deviation"),
    "shake": (0.0, 8.0, "px per frame along each axis"),
    "roll": (0.0, 5.0, "deg per frame"),
    "blur": (0.0, 8.0, "px, the Gaussian's standard deviation"),
    "jpeg": (0, 100, "quality 1-100; 0: none"),
    "speed": (0.25, 4.0, "seconds of motion per second of video"),
}


@dataclass(frozen=True)
class Degradation:
    """The artefacts of a guidance video; the defaults add none."""

    flicker: float = 0.0  # per-frame exposure gain's standard deviation, relative (0.04: 4 %)
    offset: float = 0.0  # per-frame exposure offset's standard deviation, 8-bit grey levels
    shake: float = 0.0  # camera translation per frame, standard deviation along each image axis, guidance px
    roll: float = 0.0  # camera roll per frame about the image centre, standard deviation, deg
    blur: float = 0.0  # Gaussian blur's standard deviation, guidance px (defocus, motion, a soft generator)
    jpeg: int = 0  # every frame through JPEG at this quality (1-100); 0: none
    speed: float = 1.0  # playback speed: seconds of motion a second of video shows

    @classmethod
    def parse(cls, spec: str) -> Degradation:
        """A degradation from ``spec``: preset names and ``name=value`` items, comma-separated,
        applied left to right ("realistic", "realistic,jpeg=20", "shake=1,roll=0.5",
        "speed=0.8"). ValueError names what is wrong."""
        out = cls()
        for item in (part.strip() for part in spec.split(",")):
            if not item:
                continue
            if "=" not in item:
                if item not in PRESETS:
                    raise ValueError(f"unknown degradation preset {item!r}; presets: {', '.join(PRESETS)}")
                out = replace(out, **{f.name: getattr(PRESETS[item], f.name) for f in fields(cls) if f.name != "speed"})
                continue
            name, _, text = (s.strip() for s in item.partition("="))
            if name not in LIMITS:
                raise ValueError(f"unknown artefact {name!r}; one of {', '.join(LIMITS)}")
            low, high, unit = LIMITS[name]
            try:
                value = int(text) if name == "jpeg" else float(text)
            except ValueError:
                raise ValueError(f"{name}={text!r} is not a number ({unit})") from None
            if not low <= value <= high:
                raise ValueError(f"{name}={text} is outside {low:g}..{high:g} ({unit})")
            out = replace(out, **{name: value})
        return out

    @property
    def changes_frames(self) -> bool:
        """Whether :meth:`apply` changes any frame (the speed is the simulation's)."""
        return replace(self, speed=1.0) != Degradation()

    def describe(self) -> str:
        """One line for reports: "none", or each artefact that is set with its amount."""
        units = {"flicker": "", "offset": " grey levels", "shake": " px/frame", "roll": " deg/frame"}
        units |= {"blur": " px", "jpeg": "", "speed": "x"}
        parts = []
        for f in fields(self):
            value = getattr(self, f.name)
            if value != f.default:
                shown = f"{100 * value:g} %" if f.name == "flicker" else f"{value:g}{units[f.name]}"
                parts.append(f"{'JPEG quality' if f.name == 'jpeg' else f.name} {shown}")
        return ", ".join(parts) or "none"

    def apply(self, frames: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
        """Frames [T, H, W, 3] uint8 (a rendering, H = W) shaken, area-averaged down to
        [T, size, size, 3], blurred and exposed, as float64 grey levels (not yet rounded:
        the caller adds its sensor noise, then :meth:`encode`)."""
        import cv2

        scale = frames.shape[2] / size  # rendering px per guidance px
        steps = rng.normal(0.0, 1.0, (len(frames), 3)) * (self.shake, self.shake, self.roll)
        steps[0] = 0.0  # frame 0: the camera where it was placed
        walk = np.cumsum(steps, axis=0)
        gains = 1.0 + self.flicker * rng.normal(0.0, 1.0, len(frames))
        offsets = self.offset * rng.normal(0.0, 1.0, len(frames))
        out = []
        for frame, (tx, ty, roll), gain, offset in zip(frames, walk, gains, offsets):
            if tx or ty or roll:
                h, w = frame.shape[:2]
                warp = cv2.getRotationMatrix2D((w / 2, h / 2), roll, 1.0)
                warp[:, 2] += (tx * scale, ty * scale)
                frame = cv2.warpAffine(frame, warp, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)
            small = cv2.resize(frame, (size, size), interpolation=cv2.INTER_AREA).astype(np.float64)
            if self.blur > 0:
                small = cv2.GaussianBlur(small, (0, 0), self.blur, borderType=cv2.BORDER_REFLECT101)
            out.append(max(gain, 0.0) * small + offset)
        return np.stack(out)

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Float grey levels [T, H, W, 3] rounded to uint8, then through JPEG where set."""
        import cv2

        out = np.clip(frames + 0.5, 0, 255).astype(np.uint8)
        if not self.jpeg:
            return out
        quality = [int(cv2.IMWRITE_JPEG_QUALITY), int(self.jpeg)]
        coded = []
        for frame in out:  # JPEG's luma weights are BGR's
            ok, data = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), quality)
            if not ok:
                raise RuntimeError("OpenCV could not encode a JPEG frame")
            coded.append(cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB))
        return np.stack(coded)


#: named artefact sets; "realistic": what the generated and hand-held videos that were tried
#: showed (a 4 % flicker with 3 grey levels of offset, a camera drifting by half a pixel and a
#: quarter degree a frame, a soft image, heavy JPEG)
PRESETS = {
    "none": Degradation(),
    "realistic": Degradation(flicker=0.04, offset=3.0, shake=0.5, roll=0.25, blur=0.7, jpeg=40),
}

__all__ = ["Degradation", "LIMITS", "PRESETS"]
