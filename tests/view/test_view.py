"""clflow view: the viewer of a PLY and of a simulation folder, served headless and read back
over HTTP and its websocket; the box YAML; bad input (missing file, port in use, no extra)."""

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.splat.sh import sh0_to_rgb
from clflow.view import box_yaml, count_inside, load_scene, rounded_box
from clflow_cli.main import cli
from tests.pipeline.test_written_record import sigint_as_a_terminal_sends_it
from tests.view._helpers import scene_messages, write_ply, write_simulation


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def busy_port():
    """A socket listening on a free port of 127.0.0.1 (close it when done)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    return sock


def test_box_rounds_outwards_and_reads_as_config_yaml():
    low, high = rounded_box([0.12345, -0.5, 2.0], [0.1, 0.30001, 1.0], 3)  # corners in any order
    np.testing.assert_allclose(low, [0.1, -0.5, 1.0])
    np.testing.assert_allclose(high, [0.124, 0.301, 2.0])
    assert yaml.safe_load(box_yaml(low, high)) == {
        "object": {"select": {"box": {"min": [0.1, -0.5, 1], "max": [0.124, 0.301, 2]}}}
    }
    low, high = rounded_box([0.5, 0.5, 0.5], [0.5, 0.5, 0.5], 2)  # a flat box still has min < max
    assert (high > low).all()
    means = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0001]])
    assert count_inside(means, [0, 0, 0], [1, 1, 1]) == 2  # bounds inclusive, as object.select.box


def test_ply_viewer_serves_splats_slider_and_box(tmp_path):
    pytest.importorskip("viser")
    from clflow.view import Viewer

    gaussians = write_ply(tmp_path / "scene.ply")
    scene = load_scene(tmp_path / "scene.ply", up="+z")
    assert scene.up == (0.0, 0.0, 1.0) and load_scene(tmp_path / "scene.ply", up="-x").up == (-1.0, 0.0, 0.0)
    with pytest.raises(InputError, match="up axis must be one of"):
        load_scene(tmp_path / "scene.ply", up="up")
    # colours: the rasteriser's degree-0 colour, clamped for display
    want = sh0_to_rgb(gaussians.sh[:, 0].float()).clamp(0, 1).numpy()
    np.testing.assert_allclose(scene.rgbs, want, atol=1e-6)
    np.testing.assert_allclose(scene.means[0], gaussians.means.numpy(), atol=1e-6)
    np.testing.assert_allclose(scene.covariances[0], gaussians.covariances.numpy(), rtol=1e-4, atol=1e-9)
    reports = []
    viewer = Viewer(scene, port=0, report=reports.append)
    try:
        page = urllib.request.urlopen(viewer.url(), timeout=5).read().decode()
        assert "<html" in page and viewer.url() == f"http://127.0.0.1:{viewer.port}/?token={viewer.token}"
        messages = scene_messages(viewer.url())
        by_type = {}
        for m in messages:
            by_type.setdefault(m["type"], []).append(m)
        assert [m["name"] for m in by_type["GaussianSplatsMessage"]] == ["/gaussians"]
        assert "CameraFrustumMessage" not in by_type  # a PLY has no guidance camera
        assert "GuiSliderMessage" not in by_type and viewer.frame_slider is None  # one frame: no slider
        assert sorted(m["name"] for m in by_type["TransformControlsMessage"]) == ["/box/max", "/box/min"]
        assert viewer.splats.buffer.shape == (len(gaussians), 8)
        np.testing.assert_allclose(viewer.splats.centers, scene.means[0])
        # the first box: the centres' 1..99 % bounds; typing a corner reports the new YAML
        assert reports and "    box:\n      min: [" in reports[0]
        viewer.box_min.value = (0.25, 0.25, 0.25)
        viewer.box_max.value = (0.75, 0.8, 0.7)
        box = yaml.safe_load(reports[-1])["object"]["select"]["box"]
        assert box == {"min": [0.25, 0.25, 0.25], "max": [0.75, 0.8, 0.7]}
        inside = count_inside(scene.means[0], box["min"], box["max"])
        assert 0 < inside < len(gaussians) and reports[-1].endswith(f"# {inside} of {len(gaussians)} Gaussians inside")
        assert f"{inside} of {len(gaussians)}" in viewer.box_text.content
        # the outline and the gizmos follow the fields
        np.testing.assert_allclose(viewer.box_node.dimensions, [0.5, 0.55, 0.45])
        np.testing.assert_allclose(viewer.corners[1].position, [0.75, 0.8, 0.7])
    finally:
        viewer.close()


def test_simulation_folder_in_scene_units_with_frames_and_camera(tmp_path):
    pytest.importorskip("viser")
    from clflow.view import Viewer

    means, static_means, eye, cov = write_simulation(tmp_path / "sim", up="+z", scale=2.0)
    for path in (tmp_path / "sim", tmp_path / "sim" / "render4d"):  # render4d's folder finds its parent's
        (tmp_path / "sim" / "render4d").mkdir(exist_ok=True)
        scene = load_scene(path)
        np.testing.assert_allclose(scene.means, means, atol=1e-6)  # back in the splat file's frame and units
        np.testing.assert_allclose(scene.static_means, static_means, atol=1e-6)
        np.testing.assert_allclose(scene.covariances[2, 0], cov, atol=1e-9)
        np.testing.assert_allclose(scene.up, [0, 0, 1])
        np.testing.assert_allclose(scene.camera.position.numpy(), eye, atol=1e-9)
    results = tmp_path / "results"
    results.mkdir()
    (tmp_path / "sim").rename(results / "simulation")
    assert load_scene(results).frame_count == 4  # a results folder holding simulation/
    viewer = Viewer(scene, port=0, report=lambda text: None)
    try:
        messages = scene_messages(viewer.url())
        names = [m.get("name") for m in messages if m["type"] == "GaussianSplatsMessage"]
        assert names == ["/gaussians", "/static"]
        frustum = [m for m in messages if m["type"] == "CameraFrustumMessage"]
        assert len(frustum) == 1 and frustum[0]["props"]["aspect"] == pytest.approx(64 / 48)
        np.testing.assert_allclose(viewer.frustum.position, eye, atol=1e-6)
        assert [m["props"]["label"] for m in messages if m["type"] == "GuiSliderMessage"] == ["frame"]
        assert [m["props"]["label"] for m in messages if m["type"] == "GuiButtonMessage"] == ["play"]
        assert viewer.frame_slider.max == 3
        viewer.frame_slider.value = 2  # as a browser moving the slider
        np.testing.assert_allclose(viewer.splats.centers, means[2], atol=1e-6)
        viewer.tick()  # not playing: stays
        assert viewer.frame_shown == 2
        viewer.play_button.value = True  # as a browser's click
        assert viewer.playing and viewer.play_button.label == "pause"
        viewer.tick(), viewer.tick()  # plays on and wraps to the first frame
        assert viewer.frame_shown == 0
        np.testing.assert_allclose(viewer.splats.centers, means[0], atol=1e-6)
        # browsers open behind the guidance camera, looking where it looks
        initial = viewer.server.initial_camera
        direction = (initial.look_at - initial.position) / np.linalg.norm(initial.look_at - initial.position)
        np.testing.assert_allclose(direction, scene.camera.forward.numpy(), atol=1e-9)
        assert np.linalg.norm(np.cross(eye - initial.position, direction)) < 1e-9  # on its line of sight
        # the first box is the object's at rest: it picks the object and no static Gaussian
        low, high = viewer.box
        assert count_inside(scene.rest_means, low, high) == means.shape[1]
    finally:
        viewer.close()


def test_missing_path_and_port_in_use_are_one_line(tmp_path):
    pytest.importorskip("viser")
    res = run("view", tmp_path / "nothing.ply", "--port", 0)
    assert res.exit_code == 1 and res.output.strip() == f"Error: {tmp_path / 'nothing.ply'}: no such file or folder"
    res = run("view", tmp_path, "--port", 0)  # a folder without a simulation
    assert res.exit_code == 1 and "no gaussians.npz here" in res.output and len(res.output.splitlines()) == 1
    write_ply(tmp_path / "scene.ply")
    with busy_port() as sock:
        port = sock.getsockname()[1]
        res = run("view", tmp_path / "scene.ply", "--port", port)
    assert res.exit_code == 1
    assert (
        res.output.strip() == f"Error: port {port} on 127.0.0.1 is in use (by another program or another clflow "
        "view); pick another with --port"
    )
    with pytest.raises(InputError, match="cannot resolve"):
        from clflow.view import check_port

        check_port("no-such-host.invalid", 0)


def test_a_port_taken_after_the_check_is_refused_too(tmp_path, monkeypatch):
    pytest.importorskip("viser")
    import clflow.view

    monkeypatch.setattr(clflow.view, "check_port", lambda host, port: None)  # taken between check and bind
    write_ply(tmp_path / "scene.ply")
    scene = load_scene(tmp_path / "scene.ply")
    with busy_port() as sock:
        port = sock.getsockname()[1]
        with pytest.raises(InputError, match=f"port {port} on 127.0.0.1 is in use"):
            clflow.view.Viewer(scene, port=port)  # viser alone would quietly serve on the next port


def test_without_the_extra_it_names_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser raises ImportError
    write_ply(tmp_path / "scene.ply")
    res = run("view", tmp_path / "scene.ply")
    assert res.exit_code == 1
    assert res.output.strip() == "Error: clflow view needs the optional extra 'view': pip install 'clflow[view]'"


def test_cli_serves_until_ctrl_c(tmp_path):
    pytest.importorskip("viser")
    write_ply(tmp_path / "scene.ply")
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "clflow_cli", "view", str(tmp_path / "scene.ply"), "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])},
        preexec_fn=sigint_as_a_terminal_sends_it,
    )
    lines = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stderr], daemon=True)
    reader.start()
    try:
        err = ""
        while "Ctrl-C stops" not in err:  # the viewer is up and serving
            err += lines.get(timeout=60)
        url = re.search(r"at (http://\S+); Ctrl-C stops", err)[1]
        assert re.fullmatch(rf"http://127\.0\.0\.1:{port}/\?token=[\w-]{{43}}", url)  # the token in the printed address
        page = urllib.request.urlopen(url, timeout=5).read().decode()
        assert "<html" in page
        # only 127.0.0.1 by default: another address of this machine (127.0.0.2 is loopback too) is not served
        with pytest.raises(OSError):
            urllib.request.urlopen(url.replace("127.0.0.1", "127.0.0.2"), timeout=2)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)
        out = proc.stdout.read()
        reader.join(timeout=5)
        while not lines.empty():
            err += lines.get()
    finally:
        proc.kill()
    assert proc.returncode == 130, err  # Ctrl-C: 130, as every command (docs/guarantees.md)
    assert yaml.safe_load(out.split("\n#")[0])["object"]["select"]["box"]["min"]  # stdout: the box YAML
    assert f"at {url}; Ctrl-C stops" in err and err.rstrip().endswith("stopped (Ctrl-C)")
