"""A degraded guidance (clflow_datasets.degradation): each artefact does what it says, by the
amount it says, reproducibly; a clean one is the benchmark's guidance as before; eval sysid
records it and refuses a bad one."""

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from clflow_cli.main import cli
from clflow_datasets import sysid, sysid_report
from clflow_datasets.degradation import PRESETS, Degradation
from clflow_datasets.synthetic import Resolution, SyntheticCase, degrade, make_case

TINY = Resolution(object_detail=6, floor_side=8, image=48, grid=14, frames=3, iterations=2)


def textured(frames: int = 6, size: int = 96) -> np.ndarray:
    """[frames, size, size, 3] uint8: the same smooth random texture every frame (mid-grey)."""
    import cv2

    noise = np.random.default_rng(5).uniform(0, 255, (size // 4, size // 4, 3)).astype(np.float32)
    image = cv2.resize(cv2.GaussianBlur(noise, (0, 0), 1.0), (size, size), interpolation=cv2.INTER_CUBIC)
    image = 128 + 0.6 * (image - image.mean())
    return np.repeat(np.clip(image, 0, 255).astype(np.uint8)[None], frames, axis=0)


def test_no_artefacts_is_the_area_downsampling_and_noise_it_was():
    import cv2

    frames = textured()
    for noise in (0.0, 3.0):
        plain = np.stack([cv2.resize(f, (48, 48), interpolation=cv2.INTER_AREA) for f in frames]).astype(np.float64)
        plain = plain + (np.random.default_rng(1).normal(0.0, noise, plain.shape) if noise else 0.0)
        expected = np.clip(plain + 0.5, 0, 255).astype(np.uint8)
        assert np.array_equal(degrade(frames, 48, noise, np.random.default_rng(1)), expected)


def test_a_spec_is_presets_and_items_left_to_right():
    assert Degradation.parse("") == Degradation() == PRESETS["none"]
    realistic = Degradation.parse("realistic")
    assert realistic == PRESETS["realistic"] and realistic.changes_frames and realistic.speed == 1.0
    assert Degradation.parse("realistic, jpeg=20") == Degradation(**{**vars(realistic), "jpeg": 20})
    assert Degradation.parse("speed=0.8,realistic").speed == 0.8  # a preset leaves the clock alone
    assert not Degradation.parse("speed=1.25").changes_frames
    assert Degradation.parse("shake=1,roll=0.5").describe() == "shake 1 px/frame, roll 0.5 deg/frame"
    assert "flicker 4 %" in realistic.describe() and Degradation().describe() == "none"
    for spec, message in (
        ("fancy", "unknown degradation preset 'fancy'"),
        ("wobble=1", "unknown artefact 'wobble'"),
        ("blur=soft", "blur='soft' is not a number"),
        ("jpeg=101", "jpeg=101 is outside 0..100"),
        ("speed=0", "speed=0 is outside 0.25..4"),
        ("flicker=-0.1", "flicker=-0.1 is outside"),
    ):
        with pytest.raises(ValueError, match=message):
            Degradation.parse(spec)


def test_the_shake_is_a_random_walk_of_the_amounts_given():
    """Frame 0 stays; each later frame moves from the one before by the drawn steps, which
    OpenCV's ECC registration of each frame to the first finds to a few hundredths of a pixel."""
    import cv2

    frames, shake = textured(frames=8, size=192), 1.0
    out = Degradation(shake=shake).encode(Degradation(shake=shake).apply(frames, 96, np.random.default_rng(3)))
    steps = np.random.default_rng(3).normal(0.0, 1.0, (8, 3)) * (shake, shake, 0.0)
    steps[0] = 0
    walk = np.cumsum(steps, axis=0)[:, :2]
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).astype(np.float32) for f in out]
    stop = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    found = [
        cv2.findTransformECC(grey[0], g, np.eye(2, 3, dtype=np.float32), cv2.MOTION_TRANSLATION, stop, None, 1)[1][:, 2]
        for g in grey
    ]
    assert np.abs(np.array(found) - walk).max() < 0.05
    assert np.abs(np.diff(walk, axis=0)).max() > 0.5  # the steps are the amount given, not tiny
    rolled = Degradation(roll=2.0).apply(frames, 96, np.random.default_rng(3))
    assert np.array_equal(rolled[0], Degradation().apply(frames[:1], 96, np.random.default_rng(3))[0])
    assert np.abs(rolled[-1] - rolled[0]).mean() > 2  # a rotation about the centre moves the texture


def test_the_exposure_flickers_by_its_gain_and_offset_and_blur_and_jpeg_soften():
    frames = textured()
    clean = Degradation().apply(frames, 48, np.random.default_rng(0))
    flicker = Degradation(flicker=0.05, offset=4.0)
    lit = flicker.apply(frames, 48, np.random.default_rng(7))
    rng = np.random.default_rng(7)
    rng.normal(0.0, 1.0, (len(frames), 3))  # the shake's draws come first
    gains, offsets = 1 + 0.05 * rng.normal(0.0, 1.0, len(frames)), 4.0 * rng.normal(0.0, 1.0, len(frames))
    assert np.allclose(lit, gains[:, None, None, None] * clean + offsets[:, None, None, None])
    assert np.ptp(lit.mean(axis=(1, 2, 3))) > 2  # frame to frame, the brightness jumps
    blurred = Degradation(blur=1.5).apply(frames, 48, np.random.default_rng(0))
    assert np.abs(np.diff(blurred, axis=2)).mean() < 0.7 * np.abs(np.diff(clean, axis=2)).mean()
    coded = Degradation(jpeg=20).encode(clean)
    exact = Degradation().encode(clean)
    assert 0.5 < np.abs(coded.astype(float) - exact).mean() < 8
    finest = np.abs(Degradation(jpeg=100).encode(clean).astype(float) - exact).mean()
    assert finest < 0.5 * np.abs(coded.astype(float) - exact).mean()  # the quality is the amount
    again = Degradation.parse("realistic")
    first, second = (again.encode(again.apply(frames, 48, np.random.default_rng(9))) for _ in range(2))
    assert np.array_equal(first, second)  # a seed makes the same video


def test_a_degraded_case_records_its_artefacts_and_a_speed_runs_the_truths_clock(tmp_path):
    import cv2

    case = SyntheticCase(spread=0.5)
    make_case(tmp_path / "clean", case, TINY, truth_scale=1)
    slow = Degradation(flicker=0.05, offset=3.0, jpeg=50, speed=0.5)
    make_case(tmp_path / "slow", case, TINY, truth_scale=1, degradation=slow)
    truth, opt = (yaml.safe_load((tmp_path / "slow" / n).read_text()) for n in ("config_truth.yaml", "config.yaml"))
    assert truth["simulation"]["fps"] == 2 * opt["simulation"]["fps"] == 48  # half the motion between frames
    record = json.loads((tmp_path / "slow" / "case.json").read_text())
    assert record["degradation"] == vars(slow) and "degradation" not in json.loads(
        (tmp_path / "clean" / "case.json").read_text()
    )
    clean, slow_frame = (
        cv2.imread(str(tmp_path / d / "guidance" / "002.png")).astype(float) for d in ("clean", "slow")
    )
    assert np.abs(slow_frame - clean).mean() > 1


def test_eval_sysid_takes_records_and_reports_the_degradation(tmp_path):
    settings = sysid.Settings(degradation=Degradation.parse("realistic"))
    record = sysid.settings_record(settings)
    assert record["degradation"]["jpeg"] == 40
    assert "artefacts: flicker 4 %" in sysid_report.markdown({"settings": record, "cases": {}})
    assert "artefacts" not in sysid_report.markdown({"settings": sysid.settings_record(sysid.Settings()), "cases": {}})
    assert sysid.Settings().case_options()["degradation"] == Degradation()
    older = {k: v for k, v in sysid.settings_record(sysid.Settings()).items() if k != "degradation"}
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "sysid.json").write_text(json.dumps({"settings": older, "cases": {}}))
    assert sysid._earlier_summary(tmp_path / "out", sysid.Settings(), force=False)["settings"] == older
    res = CliRunner().invoke(cli, ["eval", "sysid", "-o", str(tmp_path / "bad"), "--degrade", "shake=9"])
    assert res.exit_code == 2 and "shake=9 is outside 0..8" in res.output and not (tmp_path / "bad").exists()
