"""`clflow generate` end to end on tiny randomly initialised CogVideoX-I2V and SVD pipelines
(no weights exist here and none may be downloaded), and its refusals before any weight loads."""

import builtins
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from clflow.media import decode_video
from clflow_cli.main import cli


def run(*args):
    return CliRunner().invoke(cli, ["generate", *map(str, args)])


def prompted(model, image, out, *args, prompt="pushed"):
    """``clflow generate IMAGE --model MODEL --prompt PROMPT -o OUT ARGS...`` (CogVideoX takes a prompt)."""
    return run(image, "--model", model, "--prompt", prompt, "-o", out, *args)


def read(path):
    frames, _, fps = decode_video(path)
    return frames, fps


def test_cogvideox_makes_the_requested_frames_size_and_rate_and_records_the_run(models, object_png, tmp_path):
    out = tmp_path / "cog.mp4"
    res = prompted(
        models["cog"],
        object_png,
        out,
        "--frames",
        17,
        "--fps",
        12,
        "--steps",
        2,
        "--seed",
        3,
        prompt="the object is pushed to the left",
    )
    assert res.exit_code == 0, res.output
    frames, fps = read(out)
    assert frames.shape == (17, 48, 40, 3) and fps == pytest.approx(12)  # the image's size (--output-size image)
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["prompt"] == "the object is pushed to the left" and record["seed"] == 3 and record["steps"] == 2
    assert record["model"]["class"] == "CogVideoXImageToVideoPipeline" and record["model_size"] == [32, 16]
    assert record["device"] == "cpu" and record["versions"]["torch"].startswith("2.13.0")
    assert {"load_s", "generate_s", "write_s", "total_s"} <= set(record["timings"])

    model_size = tmp_path / "model.gif"
    res = prompted(models["cog"], object_png, model_size, "--steps", 1, "--output-size", "model")
    assert res.exit_code == 0, res.output
    assert read(model_size)[0].shape == (9, 16, 32, 3)  # the model's default frames and size


def test_the_same_seed_gives_the_same_frames(models, object_png, tmp_path):
    def frames(seed, name):
        # .mkv: lossless FFV1, so equal frames decode equal
        res = prompted(models["cog"], object_png, tmp_path / name, "--steps", 1, "--seed", seed)
        assert res.exit_code == 0, res.output
        return read(tmp_path / name)[0]

    first, again, other = frames(1, "a.mkv"), frames(1, "b.mkv"), frames(2, "c.mkv")
    assert np.array_equal(first, again)
    assert not np.array_equal(first, other)


def test_stable_video_diffusion_takes_the_image_only(models, object_png, tmp_path):
    out = tmp_path / "svd.mp4"
    res = run(
        object_png,
        "--model",
        models["svd"],
        "-o",
        out,
        "--frames",
        4,
        "--steps",
        2,
        "--fps",
        6,
        "--fit",
        "crop",
        "--output-size",
        "model",
    )
    assert res.exit_code == 0, res.output
    frames, fps = read(out)
    assert frames.shape == (4, 32, 32, 3) and fps == pytest.approx(6)
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["prompt"] is None and record["model"]["class"] == "StableVideoDiffusionPipeline"


def test_without_the_extra_it_names_the_extra_to_install(models, object_png, tmp_path, monkeypatch):
    real_import = builtins.__import__

    def no_diffusers(name, *args, **kwargs):
        if name.split(".")[0] in ("diffusers", "transformers"):
            raise ImportError(f"No module named {name!r}", name=name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_diffusers)
    res = prompted(models["cog"], object_png, tmp_path / "v.mp4")
    assert res.exit_code == 1
    assert "clflow[video]" in res.output and res.output.count("\n") == 1
    assert not (tmp_path / "v.mp4").exists()


@pytest.fixture
def no_loading(monkeypatch):
    """Fail the test if a model's weights are loaded: the refusals come before that."""
    import clflow.generate.diffusion

    def refuse(*args, **kwargs):
        raise AssertionError("weights were loaded before the input was checked")

    monkeypatch.setattr(clflow.generate.diffusion, "_load", refuse)


def _partial(models, tmp_path, drop):
    folder = tmp_path / "partial"
    shutil.copytree(models["cog"], folder)
    for path in folder.glob(drop):
        path.unlink() if path.is_file() else shutil.rmtree(path)
    return folder


@pytest.mark.parametrize(
    "case, expected",
    [
        ("missing", "model folder not found"),
        ("no index", "no model_index.json"),
        ("wrong kind", "names 'StableDiffusionPipeline'"),
        ("no transformer", "component 'transformer': folder"),
        ("no weights", "holds no weights"),
    ],
)
def test_a_model_folder_of_the_wrong_kind_says_what_layout_it_expected(
    models, object_png, tmp_path, no_loading, case, expected
):
    if case == "missing":
        folder = tmp_path / "nowhere"
    elif case == "no index":
        folder = _partial(models, tmp_path, "model_index.json")
    elif case == "wrong kind":
        folder = _partial(models, tmp_path, "nothing")
        index = json.loads((folder / "model_index.json").read_text())
        (folder / "model_index.json").write_text(json.dumps({**index, "_class_name": "StableDiffusionPipeline"}))
    elif case == "no transformer":
        folder = _partial(models, tmp_path, "transformer")
    else:
        folder = _partial(models, tmp_path, "vae/*.safetensors")
    res = prompted(folder, object_png, tmp_path / "v.mp4")
    assert res.exit_code == 1 and expected in res.output and res.output.count("\n") == 1, res.output
    if case in ("missing", "no index", "wrong kind"):  # the layouts of both families
        assert "CogVideoXImageToVideoPipeline" in res.output and "StableVideoDiffusionPipeline" in res.output
    else:  # a partial CogVideoX folder: its own layout
        assert "folders tokenizer, text_encoder, vae, transformer, scheduler" in res.output


@pytest.mark.parametrize(
    "kind, image, args, expected",
    [
        ("cog", "object", ["--frames", "6"], "1 + k x 8 frames"),
        ("cog", "object", ["--size", "64x64"], "makes only 32x16"),
        ("cog", "object", ["--size", "big"], "expected WIDTHxHEIGHT"),
        ("cog", "object", ["--prompt", " "], "needs a prompt"),
        ("svd", "object", ["--vae-tiling"], "does not offer it"),
        ("svd", "object", ["--size", "36x36"], "multiples of 8"),
        ("svd", "object", ["--guidance-scale", "0.5"], "guidance scale"),
        ("cog", "text", [], "not a readable image"),
        ("cog", "thin", [], "too thin"),
        ("cog", "missing", [], "image not found"),
        ("cog", "object", ["-o", "v.txt"], "unsupported video suffix"),
    ],
)
def test_bad_input_is_one_clear_line_before_any_weight_loads(
    models, object_png, tmp_path, no_loading, kind, image, args, expected
):
    from clflow.media import write_image

    if image == "text":
        object_png = tmp_path / "x.png"
        object_png.write_text("hello")
    elif image == "thin":
        object_png = tmp_path / "thin.png"
        write_image(object_png, np.zeros((8, 200, 3), np.uint8))
    elif image == "missing":
        object_png = tmp_path / "nothing.png"
    args = [str(tmp_path / a) if a == "v.txt" else a for a in args]
    res = prompted(models[kind], object_png, tmp_path / "v.mp4", *args)
    assert res.exit_code in (1, 2) and expected in res.output, res.output
    if res.exit_code == 1:  # 2: click's usage errors, with their usage line
        assert res.output.count("\n") == 1, res.output
    assert not (tmp_path / "v.mp4").exists()


def test_cpu_run_warns_with_an_expected_time(models):
    from clflow.generate import GenerateRequest, check_request, estimate_seconds, inspect_model

    info = inspect_model(models["cog"])
    resolved = check_request(info, GenerateRequest(prompt="pushed"))
    assert (resolved.frames, resolved.size, resolved.steps) == (9, (32, 16), 50)
    assert 0 < estimate_seconds(info, resolved) < 1  # a tiny model: well under a second
    # a CogVideoX-5b-sized transformer (11 GB of bf16 weights), 49 frames at 720x480, 50 steps: many hours
    big = type(info)(
        **{
            **info.__dict__,
            "weight_bytes": 11 * 2**30,
            "size_multiple": 16,
            "default_size": (720, 480),
            "default_frames": 49,
        }
    )
    hours = estimate_seconds(big, check_request(big, GenerateRequest(prompt="pushed")), cores=2) / 3600
    assert hours > 10


def test_fit_pads_or_crops_to_the_model_size_and_restores_the_image_area():
    from clflow.generate import fit_image, restore_frames

    image = np.zeros((48, 40, 3), np.uint8)
    image[:, :20] = 255
    padded, placement = fit_image(image, (32, 16), "pad")
    assert padded.shape == (16, 32, 3) and placement.box == (9, 0, 22, 16) and placement.restored == (40, 48)
    assert restore_frames(padded[None], placement).shape == (1, 48, 40, 3)
    cropped, placement = fit_image(image, (32, 16), "crop")
    assert cropped.shape == (16, 32, 3) and placement.box == (0, 0, 32, 16) and placement.restored == (40, 20)
