"""Probes of bad input and output through the CLI, a row each: bad output paths, a full disk, garbage input
files, outputs and grids too large. Each gives exit code 1, one line naming the problem, no
traceback, and leaves nothing partial behind."""

import errno
import importlib
import re
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Callable

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from clflow_cli.main import cli


@pytest.fixture(scope="module")
def simulation(quick_demo, tmp_path_factory):
    """A folder `clflow simulate CONFIG` wrote: gaussians.npz and PLY frames of the quick demo."""
    out = tmp_path_factory.mktemp("simulation")
    res = CliRunner().invoke(
        cli, ["simulate", str(quick_demo / "config_truth.yaml"), "-o", str(out), "--preview", "none"]
    )
    assert res.exit_code == 0, res.output
    return out


@dataclass
class Case:
    """The probe's context: ``demo`` (the quick demo), ``sim`` (a simulation folder),
    ``tmp`` (this test's folder) and ``monkeypatch``."""

    demo: object
    sim: object
    tmp: object
    monkeypatch: object

    def config(self, name: str, **changes) -> str:
        """The demo's config with ``changes`` (dotted keys), next to its scene.ply; output in tmp/out."""
        data = yaml.safe_load((self.demo / "config.yaml").read_text())
        data["output"] = str(self.tmp / "out")
        for key, value in changes.items():
            *parents, last = key.split(".")
            node = data
            for parent in parents:
                node = node[parent]
            node[last] = value
        path = self.demo / f"bad_{name}.yaml"
        path.write_text(yaml.safe_dump(data))
        return str(path)

    def a_file(self) -> str:
        (self.tmp / "afile").write_text("not a folder")
        return str(self.tmp / "afile")

    def sim_copy(self, **arrays) -> str:
        """A simulation folder whose gaussians.npz has ``arrays`` replaced."""
        data = dict(np.load(self.sim / "gaussians.npz"))
        folder = self.tmp / "sim"
        folder.mkdir()
        np.savez(folder / "gaussians.npz", **{**data, **arrays})
        return str(folder)

    def gaussians_file(self, content: bytes) -> str:
        folder = self.tmp / "sim"
        folder.mkdir()
        (folder / "gaussians.npz").write_bytes(content)
        return str(folder)

    def disk_full_on_call(self, module: str, name: str, call: int) -> None:
        """Make ``module.name`` (a module's dotted name) fail with ENOSPC on its ``call``-th call."""
        module = importlib.import_module(module)
        real, calls = getattr(module, name), []

        def failing(*args, **kwargs):
            calls.append(1)
            if len(calls) == call:
                raise OSError(errno.ENOSPC, "No space left on device", "x")
            return real(*args, **kwargs)

        self.monkeypatch.setattr(module, name, failing)

    def read_only(self) -> None:
        """Every folder reads as not writable (tests run as root, for whom chmod does not)."""
        import os

        real = os.access
        self.monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if mode & os.W_OK else real(p, mode, **kw))


def damaged_mp4(c: Case) -> str:
    """The demo's guidance video with the second half of its frame data zeroed (its index intact)."""
    data = bytearray((c.demo / "guidance.mp4").read_bytes())
    frames_at = data.find(b"mdat") + 4
    index = data.find(b"moov")
    end = index - 4 if index > frames_at else len(data)  # the index after the frames, or before them (faststart)
    start = (frames_at + end) // 2  # the first frames survive
    data[start:end] = bytes(end - start)
    (c.demo / "damaged.mp4").write_bytes(bytes(data))
    return c.config("damaged_video", video="damaged.mp4")


def huge_splats(c: Case) -> str:
    import torch

    from clflow.splat.gaussians import Gaussians
    from clflow.splat.ply import load_ply, save_ply

    g = load_ply(c.demo / "scene.ply").to(torch.float64)
    save_ply(
        c.demo / "huge.ply",
        Gaussians.from_activated(g.means, g.quats, 1000 * g.scales, g.opacities, sh=g.sh, colors=g.colors),
    )
    return c.config("huge", splats="huge.ply")


def deep_json(c: Case, name: str) -> str:
    """``name`` in the test's folder: JSON nested 200,000 levels deep (json.loads: a RecursionError)."""
    (c.tmp / name).write_text('{"a": ' + "[" * 200_000 + "]" * 200_000 + "}")
    return str(c.tmp / name)


def pickled_mask(c: Case) -> str:
    np.save(c.demo / "pickled.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    return c.config("pickled_mask", **{"object.select": {"mask": "pickled.npy"}})


def garbage_mask(c: Case) -> str:
    (c.demo / "garbage.npy").write_bytes(np.random.default_rng(0).bytes(300))
    return c.config("garbage_mask", **{"object.select": {"mask": "garbage.npy"}})


def moved_part(c: Case) -> str:
    """A config selecting the object by a PLY of the demo's Gaussians moved 0.3 scene units."""
    from clflow.splat.gaussians import Gaussians
    from clflow.splat.ply import load_ply, save_ply

    g = load_ply(c.demo / "scene.ply")
    save_ply(c.demo / "moved_part.ply", Gaussians(g.means + 0.3, g.quats, g.log_scales, g.opacity_logits, sh=g.sh))
    return c.config("moved_part", **{"object.select": {"ply": "moved_part.ply"}})


def colmap_camera(c: Case) -> str:
    """A config whose camera is an image the demo's COLMAP model (one image, a.png) lacks."""
    from clflow.splat.cameras import look_at
    from tests.recon._helpers import model_of, write_bin

    write_bin(
        c.demo / "sparse",
        model_of([look_at((0, 0.3, 1), (0, 0, 0), (0, 1, 0), fov_x=1.0, width=64, height=48, name="a.png")]),
    )
    return c.config("colmap_camera", camera={"colmap": "sparse", "image": "b.png"})


def stretching_dataparser(c: Case) -> str:
    """A config with a camera file and a dataparser transform that stretches (no rotation)."""
    import json

    (c.demo / "cams.json").write_text(
        json.dumps(
            {
                "fl_x": 50,
                "w": 64,
                "h": 48,
                "frames": [{"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]}],
            }
        )
    )
    (c.demo / "stretch.json").write_text(
        json.dumps({"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1.0})
    )
    return c.config("stretch", camera={"file": "cams.json"}, **{"scene.dataparser_transforms": "stretch.json"})


@dataclass
class Probe:
    id: str
    args: Callable[[Case], list]  # the command line, made in the test's folder
    message: str  # regular expression the one error line must match
    left: tuple[str, ...] = ()  # paths (relative to the test's folder) that must not exist afterwards
    setup: Callable[[Case], None] = field(default=lambda c: None)
    exit_code: int = 1  # 2: click's usage error (a bad option value)


PROBES = [
    # output path problems: caught before any work
    Probe(
        "simulate-parent-is-a-file",
        lambda c: ["simulate", c.config("sim"), "-o", c.a_file() + "/sub"],
        r"output folder .*afile/sub: .*afile is a file, not a folder",
    ),
    Probe(
        "optimize-output-is-a-file",
        lambda c: ["optimize", c.config("out_file", output=c.a_file())],
        r"output folder .*afile is a file, not a folder",
    ),
    Probe(
        "render-parent-is-a-file",
        lambda c: ["render", c.demo / "scene.ply", "-o", c.a_file() + "/r"],
        r"afile is a file, not a folder",
    ),
    Probe(
        "render4d-parent-is-a-file",
        lambda c: ["render4d", c.sim, "-o", c.a_file() + "/r"],
        r"afile is a file, not a folder",
    ),
    Probe(
        "query-parent-is-a-file",
        lambda c: ["query", c.demo / "guidance" / "000.png", "-o", c.a_file() + "/q.json"],
        r"afile is a file, not a folder",
    ),
    Probe(
        "simulate-read-only",
        lambda c: ["simulate", "--frames", 2, "-o", c.tmp / "s"],
        r"is not writable \(read-only file system or no permission\)",
        ("s",),
        Case.read_only,
    ),
    Probe(
        "optimize-read-only",
        lambda c: ["optimize", c.config("read_only")],
        r"is not writable \(read-only file system or no permission\)",
        ("out",),
        Case.read_only,
    ),
    Probe(
        "render4d-read-only",
        lambda c: ["render4d", c.sim, "-o", c.tmp / "r"],
        r"is not writable",
        ("r",),
        Case.read_only,
    ),
    Probe(
        "query-read-only",
        lambda c: ["query", c.demo / "guidance" / "000.png", "-o", c.tmp / "q" / "q.json"],
        r"is not writable",
        ("q",),
        Case.read_only,
    ),
    # a disk that fills up during the work: one line, nothing partial
    Probe(
        "simulate-disk-full",
        lambda c: ["simulate", c.config("disk_full"), "-o", c.tmp / "s"],
        r"no space left on device \(free some space or write elsewhere\)",
        ("s",),
        lambda c: c.disk_full_on_call("clflow.splat.ply", "save_ply", 3),
    ),
    Probe(
        "render4d-disk-full",
        lambda c: ["render4d", c.sim, "-o", c.tmp / "r"],
        r"no space left on device",
        ("r",),
        lambda c: c.disk_full_on_call("clflow.media", "write_image", 12),
    ),
    Probe(
        "render-disk-full",
        lambda c: ["render", c.demo / "scene.ply", "-o", c.tmp / "r", "--orbit", 3],
        r"no space left on device",
        ("r",),
        lambda c: c.disk_full_on_call("clflow.media", "write_image", 2),
    ),
    Probe(
        "optimize-disk-full",
        lambda c: ["optimize", c.config("opt_disk_full")],
        r"no space left on device",
        ("out/observed_flow.npz",),
        lambda c: c.disk_full_on_call("numpy", "savez_compressed", 1),
    ),
    Probe(
        "render4d-disk-has-no-room",
        lambda c: ["render4d", c.sim, "-o", c.tmp / "r"],
        r"would write up to .* \(2 sequences of 9 frames\), the disk has 0 B free; free some space or render fewer",
        ("r",),
        lambda c: c.monkeypatch.setattr("shutil.disk_usage", lambda p: SimpleNamespace(total=1, used=1, free=0)),
    ),
    # garbage input files
    Probe(
        "gaussians-npz-empty",
        lambda c: ["render4d", c.gaussians_file(b"")],
        r"gaussians.npz: the gaussians file of clflow simulate is empty \(0 bytes\)",
        ("sim/render4d",),
    ),
    Probe(
        "gaussians-npz-truncated",
        lambda c: ["render4d", c.gaussians_file((c.sim / "gaussians.npz").read_bytes()[:5000])],
        r"gaussians.npz: damaged or truncated gaussians file of clflow simulate \(BadZipFile",
        ("sim/render4d",),
    ),
    Probe(
        "gaussians-npz-random-bytes",
        lambda c: ["render4d", c.gaussians_file(np.random.default_rng(1).bytes(5000))],
        r"gaussians.npz: not a numpy .npz/.npy gaussians file of clflow simulate$",
        ("sim/render4d",),
    ),
    Probe(
        "gaussians-npz-nan-means",
        lambda c: [
            "render4d",
            c.sim_copy(
                object_means=np.where(
                    np.arange(9)[:, None, None] >= 3, np.nan, np.load(c.sim / "gaussians.npz")["object_means"]
                )
            ),
        ],
        r"object_means holds NaN or infinite values \(first in frame 3\)",
        ("sim/render4d",),
    ),
    Probe(
        "camera-file-nested-200000-deep",
        lambda c: [
            "simulate",
            c.config("deep_camera", camera={"file": deep_json(c, "cameras.json")}),
            "-o",
            c.tmp / "s",
        ],
        r"cameras.json: not a readable JSON camera file \(nested deeper than 100 levels \(line 1, column 106\)\)$",
        ("s",),
    ),
    Probe(
        "query-result-nested-200000-deep",
        lambda c: [
            "simulate",
            c.config("deep_query", material={"type": "query", "query": {"result": deep_json(c, "query.json")}}),
            "-o",
            c.tmp / "s",
        ],
        r"query.json: nested deeper than 100 levels \(line 1, column 106\)$",
        ("s",),
    ),
    Probe(
        "mask-npy-garbage",
        lambda c: ["optimize", garbage_mask(c)],
        r"garbage.npy: not a numpy .npz/.npy object mask$",
        ("out",),
    ),
    Probe(
        "mask-npy-pickled",
        lambda c: ["optimize", pickled_mask(c)],
        r"pickled.npy: the object mask holds Python objects, not plain arrays; refusing to unpickle",
        ("out",),
    ),
    Probe(
        "video-damaged-frames",
        lambda c: ["optimize", damaged_mp4(c)],
        r"damaged.mp4: damaged video: only the first \d of its 9 frames decode",
    ),
    Probe(
        "select-ply-elsewhere",
        lambda c: ["simulate", moved_part(c), "-o", c.tmp / "s"],
        r"moved_part.ply: none of its \d+ Gaussian centres lies within .* scene units of the scene's",
        ("s",),
    ),
    Probe(
        "camera-colmap-unknown-image",
        lambda c: ["simulate", colmap_camera(c), "-o", c.tmp / "s"],
        r"camera.image 'b.png' is not an image of the COLMAP model .*sparse \(a.png\)$",
        ("s",),
    ),
    Probe(
        "dataparser-transforms-stretch",
        lambda c: ["simulate", stretching_dataparser(c), "-o", c.tmp / "s"],
        r"stretch.json: the transform's 3x3 part is not a rotation",
        ("s",),
    ),
    Probe(
        "huge-gaussians",
        lambda c: ["optimize", huge_splats(c)],
        r"huge.ply: 384 of the object's 384 Gaussians are larger than the whole scene",
        ("out",),
    ),
    Probe(
        "render4d-turns-nan",
        lambda c: ["render4d", c.sim, "-o", c.tmp / "r", "--turns", "nan"],
        r"Invalid value for '--turns': 'nan' is not a finite number",
        ("r",),
        exit_code=2,
    ),
    Probe(
        "render-azimuth-inf",
        lambda c: ["render", c.demo / "scene.ply", "-o", c.tmp / "r", "--azimuth", "inf"],
        r"Invalid value for '--azimuth': 'inf' is not a finite number",
        ("r",),
        exit_code=2,
    ),
    # too large: refused with the predicted numbers and the way out, before any work
    Probe(
        "grid-1000-no-fill",
        lambda c: [
            "simulate",
            c.config("grid", **{"simulation.grid_resolution": 1000, "object.fill": {"enabled": False}}),
            "-o",
            c.tmp / "s",
        ],
        r"a 1000x\d+x1000 grid \([\d,]+ nodes\) needs .* of device memory.*use a coarser grid",
        ("s",),
    ),
    Probe(
        "grid-100000",
        lambda c: ["simulate", c.config("grid2", **{"simulation.grid_resolution": 100000}), "-o", c.tmp / "s"],
        r"a 100000x\d+x100000 grid .*use a coarser grid",
        ("s",),
    ),
    Probe(
        "simulate-1e9-frames",
        lambda c: ["simulate", c.config("frames", **{"simulation.frames": 10**9}), "-o", c.tmp / "s"],
        r"would write up to .* TB \(1,000,000,001 frames of Gaussians\), more than --max-output-gb 10; raise it or "
        r"simulate fewer frames",
        ("s",),
    ),
    Probe(
        "simulate-plain-1e9-frames",
        lambda c: ["simulate", "--frames", 10**9, "-o", c.tmp / "s"],
        r"more than --max-output-gb 10; raise it or simulate fewer --frames",
        ("s",),
    ),
    Probe(
        "simulate-memory",
        lambda c: ["simulate", "--frames", 100, "-o", c.tmp / "s", "--preview", "none"],
        r"simulating 101 frames would hold about .* in memory, the machine has 1 MB; simulate fewer --frames",
        ("s",),
        lambda c: c.monkeypatch.setattr("clflow.limits.physical_memory", lambda: 10**6),
    ),
    Probe(
        "render4d-100000-views",
        lambda c: ["render4d", c.sim, "-o", c.tmp / "r", "--views", 100000],
        r"would write up to 49.8 GB \(100,002 sequences of 9 frames\), more than --max-output-gb 10; raise it or "
        r"render fewer --views",
        ("r",),
    ),
    Probe(
        "render-100000-views",
        lambda c: ["render", c.demo / "scene.ply", "-o", c.tmp / "r", "--orbit", 100000],
        r"would write up to 78.6 GB \(100,000 views\), more than --max-output-gb 10",
        ("r",),
    ),
]


def assert_probe(probe: Probe, case: Case) -> str:
    """Run ``probe``'s command line: its exit code, one error line matching its message, no
    traceback, none of its ``left`` paths and no temporary file; returns the whole output."""
    args = [str(a) for a in probe.args(case)]
    probe.setup(case)
    res = CliRunner().invoke(cli, args)
    case.monkeypatch.undo()
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert res.exit_code == probe.exit_code and len(errors) == 1, res.output
    assert re.search(probe.message, errors[0]), errors[0]
    assert "Traceback" not in res.output
    for path in probe.left:
        assert not (case.tmp / path).exists(), path
    assert not [p for p in case.tmp.rglob("*") if ".tmp" in p.name], "temporary files left behind"
    return res.output


@pytest.mark.parametrize("probe", PROBES, ids=[p.id for p in PROBES])
def test_bad_input_is_one_line_and_leaves_nothing(probe, quick_demo, simulation, tmp_path, monkeypatch):
    assert_probe(probe, Case(quick_demo, simulation, tmp_path, monkeypatch))


def test_a_full_disk_is_named_not_the_codec(tmp_path, monkeypatch):
    import av

    from clflow.errors import ClflowError
    from clflow.media import write_video

    frames = np.zeros((2, 16, 16, 3), np.uint8)
    monkeypatch.setattr("shutil.disk_usage", lambda p: SimpleNamespace(total=1, used=1, free=0))

    def full(*args, **kwargs):
        raise av.error.FFmpegError(28, "No space left on device")

    monkeypatch.setattr(av, "open", full)
    with pytest.raises(ClflowError, match=r"v.mp4: no space left on the device \(0 B free\)"):
        write_video(tmp_path / "v.mp4", frames, 24.0)
    assert list(tmp_path.iterdir()) == []


def test_atomic_dir_moves_its_entries_in_or_leaves_the_folder_as_it_was(tmp_path):
    from clflow.fileio import WRITTEN_RECORD, atomic_dir

    out = tmp_path / "out"
    with atomic_dir(out) as tmp:
        (tmp / "frames").mkdir()
        (tmp / "frames" / "000.png").write_text("a")
        (tmp / "video.mp4").write_text("a")
    (out / "mine.txt").write_text("the user's")
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as tmp:
            (tmp / "video.mp4").write_text("b")
            raise RuntimeError
    assert (out / "video.mp4").read_text() == "a"
    with atomic_dir(out) as tmp:
        (tmp / "frames").mkdir()
        (tmp / "frames" / "001.png").write_text("b")
    assert sorted(p.name for p in out.rglob("*")) == [WRITTEN_RECORD, "001.png", "frames", "mine.txt", "video.mp4"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_records_nested_too_deep_read_as_damaged_ones(tmp_path):
    """The records kept in output folders (a budget's choice, the results page's params.json,
    a sweep run's result and inputs), nested 200,000 deep: read as damaged, not a traceback."""
    from clflow.fileio import atomic_write_text
    from clflow.pipeline.fit.budget import load_choice
    from clflow.pipeline.report import _read
    from clflow.sweep.runner import _started_with
    from clflow.sweep.study import previous_record

    for name in ("result.json", "inputs.json"):  # clflow's own, damaged
        atomic_write_text(tmp_path / name, '{"a": ' + "[" * 200_000 + "]" * 200_000 + "}")
    assert load_choice(tmp_path / "result.json", {}) is None and _read(tmp_path / "result.json") is None
    assert previous_record(tmp_path) is None
    assert _started_with(tmp_path, {"a": 1})  # other inputs than these: the run starts over
