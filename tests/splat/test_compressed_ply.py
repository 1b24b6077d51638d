"""Compressed PLY (clflow.splat.compressed_ply): the layout SuperSplat / PlayCanvas read,
checked against hand-packed bits and by a round trip within each field's quantisation step."""

import dataclasses
import math
import struct

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.splat.compressed_ply import CHUNK, CHUNK_FIELDS, morton_order, save_compressed_ply
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import load_ply
from clflow.splat.ply_format import read_ply_elements
from clflow.splat.sh import SH_C0


def random_gaussians(n, seed, degree=3):
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randn(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    return Gaussians(r(n, 3) * torch.tensor([1.0, 2.0, 0.5]), r(n, 4), r(n, 3) - 3, r(n), sh=r(n, (degree + 1) ** 2, 3))


def with_objects(g, objects):
    """``g`` with the feature ``object`` [N]."""
    return dataclasses.replace(g, features=objects.reshape(-1, 1).to(g.means.dtype), feature_names=("object",))


def per_chunk_step(values, bits):
    """[N, D] quantisation step of each value: its chunk's range / (2^bits - 1)."""
    chunk = np.arange(len(values)) // CHUNK
    starts = np.arange(0, len(values), CHUNK)
    span = np.maximum.reduceat(values, starts) - np.minimum.reduceat(values, starts)
    return span[chunk] / (2.0 ** np.array(bits) - 1)


@pytest.mark.parametrize("n, degree", [(1000, 3), (256, 1), (5, 0)])
def test_round_trip_within_the_quantisation_step(tmp_path, n, degree):
    g = random_gaussians(n, seed=n, degree=degree)
    save_compressed_ply(tmp_path / "g.compressed.ply", g)
    back = load_ply(tmp_path / "g.compressed.ply")  # load_ply reads the compressed layout too
    order = morton_order(g.means.numpy())
    want = g.select(torch.from_numpy(order))
    num = lambda t: t.double().numpy()  # noqa: E731
    assert len(back) == n and back.sh.shape == want.sh.shape
    slack = 1e-6  # float32 bounds and values
    for got, truth, bits in ((back.means, want.means, (11, 10, 11)), (back.log_scales, want.log_scales, (11, 10, 11))):
        err = np.abs(num(got) - num(truth))
        assert (err <= 0.5 * per_chunk_step(num(truth), bits) * (1 + 1e-6) + slack).all()
    rgb = lambda s: SH_C0 * num(s[:, 0]) + 0.5  # noqa: E731
    assert (np.abs(rgb(back.sh) - rgb(want.sh)) <= 0.5 * per_chunk_step(rgb(want.sh), (8, 8, 8)) + slack).all()
    assert np.abs(num(back.opacities) - num(want.opacities)).max() <= 0.5 / 255 + slack
    q, p = num(torch.nn.functional.normalize(want.quats, dim=-1)), num(back.unit_quats)
    p *= np.sign((q * p).sum(1, keepdims=True))  # q and -q are one rotation
    half = 0.5 * math.sqrt(2) / 1023  # of the three smaller components; the largest follows from them
    smaller = np.argsort(np.abs(q), 1)[:, :3]
    assert np.take_along_axis(np.abs(p - q), smaller, 1).max() <= half + slack and np.abs(p - q).max() <= 6 * half
    if degree:
        rest, truth = num(back.sh[:, 1:]), np.clip(num(want.sh[:, 1:]), -4, 4)
        assert np.abs(rest - truth).max() <= 1 / 32 + slack
        inner = np.abs(truth) < 4 - 1 / 32  # away from the ends, decoded at the middle of the byte's interval
        assert np.abs(rest - truth)[inner].max() <= 1 / 64 + slack
    if n >= CHUNK:  # a quarter or less of the float32 file's size
        assert (tmp_path / "g.compressed.ply").stat().st_size < 0.3 * 4 * n * (14 + 3 * (degree + 1) ** 2)


def test_the_layout_matches_the_format(tmp_path):
    """Header, element order and the bits of known values, packed by hand from the format."""
    g = Gaussians(
        torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 4.0]]),
        torch.tensor([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]),
        torch.tensor([[-1.0, -2.0, -3.0], [-1.0, -1.0, -1.0]]),
        torch.tensor([0.0, 50.0]),
        sh=torch.cat([torch.zeros(2, 1, 3), torch.full((2, 3, 3), 0.5)], 1),
    )
    path = tmp_path / "g.compressed.ply"
    save_compressed_ply(path, g)
    data = path.read_bytes()
    header = data[: data.index(b"end_header\n") + 11].decode()
    lines = [line for line in header.splitlines() if not line.startswith("comment")]
    assert lines[:4] == ["ply", "format binary_little_endian 1.0", "element chunk 1"] + [
        f"property float {CHUNK_FIELDS[0]}"
    ]
    assert lines[3:21] == [f"property float {name}" for name in CHUNK_FIELDS]
    assert lines[21:26] == ["element vertex 2"] + [
        f"property uint packed_{k}" for k in ("position", "rotation", "scale", "color")
    ]
    assert lines[26:] == ["element sh 2"] + [f"property uchar f_rest_{i}" for i in range(9)] + ["end_header"]
    body = data[len(header) :]
    bounds = struct.unpack("<18f", body[:72])
    assert bounds[:6] == (0, 0, 0, 2, 1, 4) and bounds[6:12] == (-1, -2, -3, -1, -1, -1)
    vertices = struct.unpack("<8I", body[72:104])  # in Morton order: the origin first
    assert vertices[0] == 0 and vertices[4] == 0xFFFFFFFF  # positions: the chunk's min and max corners
    assert vertices[1] == (0 << 30) | (512 << 20) | (512 << 10) | 512  # w largest, x y z at 0
    assert vertices[5] == (2 << 30) | (512 << 20) | (512 << 10) | 512  # -y largest: flipped positive
    assert vertices[2] == (0 << 21) | (0 << 11) | 0 and vertices[6] == (0 << 21) | (1023 << 11) | 2047
    assert vertices[3] & 0xFF == 128 and vertices[7] & 0xFF == 255  # sigmoid(0) = 0.5, sigmoid(50) = 1
    assert body[104:] == bytes([int((0.5 / 8 + 0.5) * 256)] * 18)  # f_rest 0.5 -> 144


def test_a_file_packed_by_hand_reads_back(tmp_path):
    """One Gaussian built from the format's description, not by clflow's writer."""
    head = [
        "ply",
        "format binary_little_endian 1.0",
        "element chunk 1",
        *(f"property float {n}" for n in CHUNK_FIELDS),
        "element vertex 1",
        *(f"property uint packed_{k}" for k in ("position", "rotation", "scale", "color")),
        "end_header",
    ]
    bounds = [0, 0, 0, 1, 1, 1, -2, -2, -2, 0, 0, 0, 0, 0, 0, 1, 1, 1]
    third = round(1023 * (0.5 * math.sqrt(0.5) + 0.5))  # x = 0.5 in the smallest-three code
    position = (2047 << 21) | (0 << 11) | 1023  # x = 1, y = 0, z = 1023 / 2047
    rotation = (0 << 30) | (third << 20) | (512 << 10) | 512
    color = (255 << 24) | (0 << 16) | (51 << 8) | 204  # r = 1, g = 0, b = 0.2, alpha = 0.8
    (tmp_path / "h.ply").write_bytes(
        ("\n".join(head) + "\n").encode()
        + struct.pack("<18f", *bounds)
        + struct.pack("<4I", position, rotation, 0xFFFFFFFF, color)
    )
    g = load_ply(tmp_path / "h.ply")
    torch.testing.assert_close(g.means[0], torch.tensor([1.0, 0.0, 1023 / 2047]))
    torch.testing.assert_close(g.log_scales[0], torch.zeros(3))
    x, yz = ((v / 1023 - 0.5) / math.sqrt(0.5) for v in (third, 512))  # 512 / 1023 is just above 1/2
    w = math.sqrt(1 - x * x - 2 * yz * yz)
    torch.testing.assert_close(g.quats[0], torch.tensor([w, x, yz, yz]))
    torch.testing.assert_close(g.sh[0, 0] * SH_C0 + 0.5, torch.tensor([1.0, 0.0, 0.2]))
    torch.testing.assert_close(g.opacities[0], torch.tensor(0.8))


def test_bad_compressed_files(tmp_path):
    g = random_gaussians(300, 1)
    save_compressed_ply(tmp_path / "g.ply", g)
    data = (tmp_path / "g.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-100])
    with pytest.raises(InputError, match=r"cut.ply: truncated: the header declares 300 sh entries"):
        load_ply(tmp_path / "cut.ply")
    (tmp_path / "chunks.ply").write_bytes(data.replace(b"element chunk 2", b"element chunk 1", 1))
    with pytest.raises(InputError, match=r"chunks.ply: 1 chunks for 300 Gaussians"):
        load_ply(tmp_path / "chunks.ply")
    (tmp_path / "signed.ply").write_bytes(data.replace(b"property uchar f_rest_0\n", b"property char f_rest_0\n", 1))
    with pytest.raises(InputError, match=r"signed.ply: the sh element's properties must be uchar"):
        load_ply(tmp_path / "signed.ply")
    assert set(read_ply_elements(tmp_path / "g.ply", ("vertex",), optional=("sh", "nope"))) == {"vertex", "sh"}


@pytest.mark.parametrize("labels", [[0], [-1, 0, 1, 2]])
def test_the_object_feature_round_trips_as_runs_of_vertices(tmp_path, labels):
    """Each Gaussian's object (one object, or static -1 and three) comes back with it; the
    layout stays the one PlayCanvas reads: the runs are a header comment, no new property."""
    n = 700
    g = random_gaussians(n, seed=7, degree=1)
    objects = torch.tensor(labels, dtype=torch.float64)[
        torch.randint(len(labels), (n,), generator=torch.Generator().manual_seed(8))
    ]
    g = with_objects(g, objects)
    path = tmp_path / "g.compressed.ply"
    save_compressed_ply(path, g)
    back = load_ply(path)
    assert back.feature_names == ("object",)
    got = back.features[:, 0].long()
    assert got.tolist() == sorted(got.tolist())  # object by object
    nearest = torch.cdist(back.means.double(), g.means).argmin(1)  # each read Gaussian's written one
    assert torch.equal(got, objects[nearest].long()) and len(set(nearest.tolist())) == n
    header = path.read_bytes().split(b"end_header")[0].decode()
    runs = " ".join(f"{v}:{int((objects == v).sum())}" for v in sorted(set(labels)))
    assert f"comment clflow objects {runs}\n" in header
    assert [line for line in header.splitlines() if line.startswith("property uint")] == [
        f"property uint packed_{k}" for k in ("position", "rotation", "scale", "color")
    ]
    assert len([line for line in header.splitlines() if line.startswith("element")]) == 3  # chunk, vertex, sh
    # without the feature: no runs, no feature
    save_compressed_ply(tmp_path / "plain.compressed.ply", random_gaussians(10, 1))
    assert load_ply(tmp_path / "plain.compressed.ply").features is None


def test_bad_object_runs_are_refused(tmp_path):
    g = random_gaussians(20, 3, degree=0)
    labelled = with_objects(g, torch.zeros(20))
    save_compressed_ply(tmp_path / "g.ply", labelled)
    data = (tmp_path / "g.ply").read_bytes()
    assert b"comment clflow objects 0:20\n" in data
    for name, runs in (("short", b"0:19"), ("word", b"0:x"), ("twice", b"0:20\ncomment clflow objects 0:20")):
        (tmp_path / f"{name}.ply").write_bytes(data.replace(b"objects 0:20", b"objects " + runs, 1))
        with pytest.raises(InputError, match=rf"{name}.ply: the header's 'clflow objects' comment must be one line"):
            load_ply(tmp_path / f"{name}.ply")
    half = with_objects(g, torch.full((20,), 0.5))
    with pytest.raises(InputError, match="h.ply: the feature 'object' must hold integers"):
        save_compressed_ply(tmp_path / "h.ply", half)
