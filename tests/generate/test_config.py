"""``video: {generate: ...}`` in a scene config: checked with the config, made as the first
step of `clflow optimize` (the tiny CogVideoX of _helpers.py), cached by its inputs, and
the motion prompt filled from the forces."""

import json

import pytest
import yaml
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.scene.config import load_config


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The QUICK demo's scene.ply and its config as a dict (96x96 camera, 8 frames at 24 fps)."""
    from clflow_datasets.demo import DEMO, QUICK
    from clflow_datasets.synthetic import case_config, write_scene

    folder = tmp_path_factory.mktemp("scene")
    write_scene(folder, DEMO, QUICK)
    return folder, case_config(DEMO, QUICK, {**DEMO.truth, **DEMO.guess}, optimize=True)


def write(scene, tmp_path, **generate):
    folder, base = scene
    data = json.loads(json.dumps(base))
    data["splats"] = str(folder / "scene.ply")
    data["output"] = str(tmp_path / "results")
    data["video"] = {"generate": generate}
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_config_reads_generate_and_leaves_video_to_be_made(scene, tmp_path, models):
    cfg = load_config(
        write(
            scene,
            tmp_path,
            model=str(models["cog"]),
            seed=4,
            steps=1,
            size="32x16",
            prompt="the cube is pushed",
            cpu_offload=False,
        )
    )
    assert cfg.video is None and cfg.generate.model == models["cog"].resolve()
    assert (cfg.generate.seed, cfg.generate.steps, cfg.generate.size, cfg.generate.prompt) == (
        4,
        1,
        (32, 16),
        "the cube is pushed",
    )


@pytest.mark.parametrize(
    "generate, expected",
    [
        ({}, "video.generate: is required"),
        ({"model": "nowhere"}, "video.generate.model: "),
        ({"frames": 9, "fps": 48}, "video.generate.frames: 9 frames at 48 fps last 0.167 s, the simulation 0.333 s"),
        ({"frames": 10}, "video.generate.frames: "),
        ({"size": [64, 64]}, "video.generate.size: "),
        ({"size": "wide"}, "video.generate.size: "),
        ({"seed": -1}, "video.generate.seed: "),
        ({"seed": 2**64}, "video.generate.seed: an integer of 20 digits is beyond any value a config takes"),
        ({"steps": 10**5}, "video.generate.steps: must be an integer in [1, 10000], got 100000"),
        ({"frames": 10**5}, "video.generate.frames: must be an integer in [2, 10000], got 100000"),
        ({"fps": 1e-308}, "video.generate.fps: must be in [0.001, 1e+06], got 1e-308"),
        ({"guidance_scale": 1e308}, "video.generate.guidance_scale: must be in [0, 1000], got 1e+308"),
        ({"size": [100000, 64]}, "video.generate.size: must be at most 16384 pixels a side, got 100000x64"),
        ({"size": "9" * 5000 + "x16"}, "video.generate.size: must be WIDTHxHEIGHT or"),
        ({"prompt_template": "the {thing} moves"}, "video.generate.prompt_template: has the unknown placeholder"),
        ({"prompt": ""}, "video.generate.prompt: is empty"),
        ({"vae_tiling": "yes"}, "video.generate.vae_tiling: must be true or false"),
        ({"fit": "stretch"}, "video.generate.fit: must be one of pad, crop"),
        ({"image": "missing.png"}, "video.generate.image: file not found"),
        ({"colour": 1}, "video.generate.colour: unknown key"),
    ],
)
def test_bad_generate_keys_are_named(scene, tmp_path, models, generate, expected):
    if generate and "model" not in generate:
        generate = {"model": str(models["cog"]), **generate}
    with pytest.raises(InputError) as err:
        load_config(write(scene, tmp_path, **generate))
    assert expected in str(err.value)


def test_generate_makes_one_view(scene, tmp_path, models):
    path = write(scene, tmp_path, model=str(models["cog"]))
    data = yaml.safe_load(path.read_text())
    data["camera"] = [data["camera"], data["camera"]]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match="video.generate: makes one guidance view's video"):
        load_config(path)


def test_the_motion_prompt_comes_from_the_forces_and_can_be_overridden(scene, tmp_path, models):
    import dataclasses

    from clflow.pipeline.generated_video import motion_prompt
    from clflow.regions import Region
    from clflow.scene.config import ForceStage

    cfg = load_config(write(scene, tmp_path, model=str(models["cog"]), object="jelly cube"))
    prompt = motion_prompt(cfg)  # the demo: a short push along +x
    assert "The jelly cube is hit and pushed to the right" in prompt and "elastic" in prompt
    left = ForceStage(Region("all"), (-3.0, 0.0, 0.0), "force", 0.2, float("inf"))
    assert "is pushed to the left after 0.2 s" in motion_prompt(dataclasses.replace(cfg, forces=(left,)))
    thrown = dataclasses.replace(
        cfg, forces=(), objects=(dataclasses.replace(cfg.objects[0], velocity=(0.0, 1.0, -1.0)),)
    )
    assert "thrown upwards and away from the camera" in motion_prompt(thrown)
    assert (
        motion_prompt(dataclasses.replace(cfg, forces=()), "{object}: {motion}") == "jelly cube: falling under gravity"
    )
    cfg = load_config(
        write(scene, tmp_path, model=str(models["cog"]), prompt_template="A {material} {object} {motion}.")
    )
    assert motion_prompt(cfg) == "A elastic object hit and pushed to the right."


def test_optimize_makes_the_guidance_video_first_caches_it_and_takes_it(scene, tmp_path, models, monkeypatch):
    """Config level: the generated video is made from the rendered guidance view, it is the
    camera's size and covers the simulated time (guidance_video, what `clflow optimize`
    reads first), and the same inputs reuse it."""
    import clflow.generate
    from clflow.pipeline.fit.guidance import guidance_video
    from clflow.pipeline.generated_video import ensure_guidance_video
    from clflow.scene.load import guidance_camera

    cfg = load_config(write(scene, tmp_path, model=str(models["cog"]), steps=1, seed=2))
    made = ensure_guidance_video(cfg)
    assert made.video.parent == cfg.output / "generated" and made.video.suffix == ".mp4"
    record = json.loads(made.video.with_suffix(".json").read_text())
    assert "hit and pushed to the right" in record["prompt"] and record["image"] == "rendered scene"
    assert made.video.with_suffix(".input.png").is_file()
    video = guidance_video(made, made.video, guidance_camera(made), made.simulation.frames)
    assert video.frames.shape == (9, 96, 96, 3)  # simulation.frames + 1 at the camera's size

    def no_second_run(*args, **kwargs):
        raise AssertionError("the cached video was made again")

    monkeypatch.setattr(clflow.generate, "generate_video", no_second_run)
    assert ensure_guidance_video(cfg).video == made.video
    other = load_config(write(scene, tmp_path, model=str(models["cog"]), steps=1, seed=3))
    with pytest.raises(AssertionError, match="made again"):  # another seed: another video
        ensure_guidance_video(other)


def test_a_given_image_must_be_the_guidance_cameras_size(scene, tmp_path, models, object_png):
    from clflow.pipeline.generated_video import ensure_guidance_video

    cfg = load_config(write(scene, tmp_path, model=str(models["cog"]), image=str(object_png)))
    with pytest.raises(InputError, match="video.generate.image: .* is 40x48 px, the guidance camera 96x96"):
        ensure_guidance_video(cfg)


@pytest.mark.slow
def test_clflow_optimize_runs_on_a_generated_video(scene, tmp_path, models):
    from clflow_cli.main import cli

    path = write(scene, tmp_path, model=str(models["cog"]), steps=1)
    # a random-weight model's frames look nothing like the scene: the guidance checks refuse
    # them (the plumbing is what this tests), --force-video goes on with a warning
    res = CliRunner().invoke(cli, ["optimize", str(path), "--iterations", "1"])
    assert res.exit_code == 1 and "does not look like the scene" in res.output
    assert "generating the guidance video: step 1/1" in res.output
    res = CliRunner().invoke(cli, ["optimize", str(path), "--iterations", "1", "--force-video"])
    assert res.exit_code == 0, res.output
    assert "generating the guidance video" not in res.output  # the cached one
    assert (tmp_path / "results" / "params.json").is_file()
    assert len(list((tmp_path / "results" / "generated").glob("guidance-*.mp4"))) == 1
