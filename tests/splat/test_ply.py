"""3DGS and point-cloud PLY files: exact layout, activations, round trips and bad files."""

import struct

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import load_ply, read_ply_vertices, save_ply, write_ply_vertices
from clflow.splat.sh import sh0_to_rgb


def inria_property_names(degree: int) -> list[str]:
    """The vertex properties INRIA's trainer writes (construct_list_of_attributes), spelled out."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += ["f_rest_%d" % i for i in range(3 * ((degree + 1) ** 2 - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def write_inria_ply(path, values: np.ndarray, names: list[str], fmt: str = "binary_little_endian") -> bytes:
    """A PLY file as a trainer writes it, value by value with struct (no clflow code)."""
    header = "ply\nformat %s 1.0\nelement vertex %d\n" % (fmt, len(values))
    header += "".join("property float %s\n" % name for name in names) + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join("%.9g" % v for v in row) + "\n" for row in values).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        body = b"".join(struct.pack(order + "%df" % len(row), *row) for row in values)
    data = header.encode() + body
    path.write_bytes(data)
    return data


def random_attributes(n: int, degree: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(n, len(inria_property_names(degree)))).astype(np.float32)
    values[:, 3:6] = 0  # normals
    return values


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_trainer_layout_loads_with_activations_and_writes_back_identically(tmp_path, degree):
    names = inria_property_names(degree)
    values = random_attributes(7, degree)
    original = write_inria_ply(tmp_path / "in.ply", values, names)
    col = {name: torch.from_numpy(values[:, j].copy()) for j, name in enumerate(names)}

    g = load_ply(tmp_path / "in.ply")

    assert g.sh_degree == degree and len(g) == 7 and g.dtype == torch.float32
    assert torch.equal(g.means, torch.stack([col["x"], col["y"], col["z"]], 1))
    scales = torch.stack([col["scale_0"], col["scale_1"], col["scale_2"]], 1)
    assert torch.equal(g.scales, torch.exp(scales))
    assert torch.equal(g.opacities, torch.sigmoid(col["opacity"]))
    quats = torch.stack([col["rot_0"], col["rot_1"], col["rot_2"], col["rot_3"]], 1)
    assert torch.allclose(g.unit_quats, quats / quats.norm(dim=1, keepdim=True), rtol=0, atol=1e-6)
    for c in range(3):
        assert torch.equal(g.sh[:, 0, c], col[f"f_dc_{c}"])
        per_channel = (degree + 1) ** 2 - 1
        for k in range(1, per_channel + 1):  # f_rest is channel-major
            assert torch.equal(g.sh[:, k, c], col[f"f_rest_{c * per_channel + k - 1}"])
    assert g.features is None

    save_ply(tmp_path / "out.ply", g)
    assert (tmp_path / "out.ply").read_bytes() == original


def test_big_endian_and_ascii_files_load_the_same_values(tmp_path):
    names = inria_property_names(1)
    values = random_attributes(5, 1, seed=1)
    write_inria_ply(tmp_path / "le.ply", values, names)
    write_inria_ply(tmp_path / "be.ply", values, names, fmt="binary_big_endian")
    write_inria_ply(tmp_path / "a.ply", values, names, fmt="ascii")
    reference = load_ply(tmp_path / "le.ply")
    for other in ("be.ply", "a.ply"):
        g = load_ply(tmp_path / other)
        for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            assert torch.equal(getattr(g, field), getattr(reference, field)), (other, field)


def test_round_trip_is_bit_exact_binary_and_ascii_with_features(tmp_path):
    gen = torch.Generator().manual_seed(3)
    g = Gaussians(
        means=torch.randn(9, 3, generator=gen),
        quats=torch.randn(9, 4, generator=gen),
        log_scales=torch.randn(9, 3, generator=gen) - 3,
        opacity_logits=torch.randn(9, generator=gen),
        sh=torch.randn(9, 9, 3, generator=gen) * 1e-3,
        features=torch.randn(9, 2, generator=gen),
        feature_names=("flow_u", "flow_v"),
    )
    for ascii in (False, True):
        save_ply(tmp_path / "g.ply", g, ascii=ascii)
        back = load_ply(tmp_path / "g.ply")
        assert back.feature_names == ("flow_u", "flow_v")
        for field in ("means", "quats", "log_scales", "opacity_logits", "sh", "features"):
            assert torch.equal(getattr(back, field), getattr(g, field)), (ascii, field)
    header = (tmp_path / "g.ply").read_bytes().split(b"end_header")[0].decode()
    assert header.index("rot_3") < header.index("flow_u")  # 3DGS layout first, extras after


def test_rgb_colors_are_written_as_degree_zero_sh(tmp_path):
    rgb = torch.tensor([[1.0, 0.0, 0.25], [0.5, 0.5, 0.5]])
    g = Gaussians.from_activated(
        torch.zeros(2, 3),
        torch.tensor([[1.0, 0, 0, 0]] * 2),
        torch.full((2, 3), 0.1),
        torch.full((2,), 0.5),
        colors=rgb,
    )
    save_ply(tmp_path / "c.ply", g)
    back = load_ply(tmp_path / "c.ply")
    assert back.sh_degree == 0
    assert torch.allclose(sh0_to_rgb(back.sh[:, 0]), rgb, atol=1e-6)


def test_point_cloud_with_uchar_colors_becomes_isotropic_gaussians(tmp_path):
    xyz = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]], dtype=np.float32)
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255], [0, 0, 0]], dtype=np.uint8)
    table = np.empty(5, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for j, axis in enumerate("xyz"):
        table[axis] = xyz[:, j]
    for j, channel in enumerate(("red", "green", "blue")):
        table[channel] = rgb[:, j]
    write_ply_vertices(tmp_path / "pc.ply", table)
    g = load_ply(tmp_path / "pc.ply")
    assert g.sh_degree == 0 and len(g) == 5
    assert torch.allclose(sh0_to_rgb(g.sh[:, 0]), torch.from_numpy(rgb / 255.0).float(), atol=1e-6)
    # 3DGS's rule: RMS distance to the 3 nearest neighbours; point 0's are at 1, 2, 3 m.
    assert g.scales[0].tolist() == pytest.approx([np.sqrt(14 / 3)] * 3, rel=1e-6)
    assert g.scales[2].tolist() == pytest.approx([np.sqrt((1 + 1 + 4) / 3)] * 3, rel=1e-6)
    assert torch.allclose(g.opacities, torch.full((5,), 0.1))
    assert torch.equal(g.unit_quats, torch.tensor([[1.0, 0, 0, 0]] * 5))


def test_point_cloud_without_colors_is_grey_and_takes_a_given_scale(tmp_path):
    table = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f8")])
    table["x"] = np.arange(3)
    write_ply_vertices(tmp_path / "pc.ply", table, ascii=True)
    g = load_ply(tmp_path / "pc.ply", point_scale=0.02, point_opacity=0.9)
    assert torch.allclose(sh0_to_rgb(g.sh[:, 0]), torch.full((3, 3), 0.5))
    assert torch.allclose(g.scales, torch.full((3, 3), 0.02))
    assert torch.allclose(g.opacities, torch.full((3,), 0.9))


def test_point_cloud_with_float_rgb_in_unit_range(tmp_path):
    table = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("r", "f4"), ("g", "f4"), ("b", "f4")])
    table["x"] = [0, 1]
    table["r"], table["g"], table["b"] = [0.2, 1.0], [0.4, 0.0], [0.6, 0.5]
    write_ply_vertices(tmp_path / "pc.ply", table)
    g = load_ply(tmp_path / "pc.ply")
    assert torch.allclose(sh0_to_rgb(g.sh[:, 0]), torch.tensor([[0.2, 0.4, 0.6], [1.0, 0.0, 0.5]]), atol=1e-6)


def test_elements_around_the_vertex_element_are_skipped(tmp_path):
    body = struct.pack("<B", 7) + struct.pack("<3f", 1, 2, 3) + struct.pack("<B3i", 3, 0, 0, 0)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment made by a test\nelement camera 1\nproperty uchar id\n"
        "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    (tmp_path / "m.ply").write_bytes(header.encode() + body)
    columns = read_ply_vertices(tmp_path / "m.ply")
    assert [columns[k].item() for k in "xyz"] == [1, 2, 3]


def _bad_file(tmp_path, degree=0, edit=None, drop=None):
    names = inria_property_names(degree)
    values = random_attributes(4, degree)
    if edit:
        edit(values, names)
    if drop:
        keep = [j for j, name in enumerate(names) if name != drop]
        values, names = values[:, keep], [names[j] for j in keep]
    write_inria_ply(tmp_path / "bad.ply", values, names)
    return tmp_path / "bad.ply"


def _set(name, value, row=2):
    def edit(values, names):
        values[row, names.index(name)] = value

    return edit


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: _bad_file(p, drop="opacity"), "missing attributes: opacity"),
        (lambda p: _bad_file(p, drop="rot_2"), "missing attributes: rot_2"),
        (lambda p: _bad_file(p, degree=1, drop="f_rest_8"), "not a multiple of 3"),
        (lambda p: _bad_file(p, degree=1, drop="f_rest_3"), "not numbered"),
        (lambda p: _bad_file(p, edit=_set("scale_1", np.nan)), "'scale_1' has 1 non-finite values (first: vertex 2"),
        (lambda p: _bad_file(p, edit=_set("x", np.inf, row=0)), "'x' has 1 non-finite values (first: vertex 0"),
        (lambda p: _bad_file(p, edit=_set("scale_0", -200.0)), "scales are 0 after activation (first: Gaussian 2"),
        (lambda p: _bad_file(p, edit=lambda v, n: v[1, n.index("rot_0") :].fill(0)), "degenerate quaternions"),
    ],
)
def test_bad_gaussian_attributes_raise_input_errors_naming_the_file(tmp_path, make, message):
    path = make(tmp_path)
    with pytest.raises(InputError, match="bad.ply") as info:
        load_ply(path)
    assert message in str(info.value)


def test_sh_count_that_is_no_degree_is_rejected(tmp_path):
    names = inria_property_names(0) + [f"f_rest_{i}" for i in range(6)]
    values = np.zeros((2, len(names)), dtype=np.float32)
    values[:, names.index("rot_0")] = 1
    write_inria_ply(tmp_path / "odd.ply", values, names)
    with pytest.raises(InputError, match="6 f_rest attributes"):
        load_ply(tmp_path / "odd.ply")


@pytest.mark.parametrize(
    "data, message",
    [
        (b"PK\x03\x04 zip", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n", "no 'end_header'"),
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "header line 2"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n1\n", "PLY scalar type"),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no 'vertex' element"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n1 1\n",
            "appears twice",
        ),
        (b"ply\nelement vertex 0\nend_header\n", "no 'format' line"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n",
            "truncated",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n4 5\n",
            "vertex 1 has 2 values",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 two 3\n",
            "not a number",
        ),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n", "no z"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty uint packed_position\nend_header\n1\n", "compressed"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n1 2 3 4\n",
            "need all of red, green, blue",
        ),
    ],
)
def test_malformed_files_raise_input_errors(tmp_path, data, message):
    (tmp_path / "m.ply").write_bytes(data)
    with pytest.raises(InputError, match="m.ply") as info:
        load_ply(tmp_path / "m.ply")
    assert message in str(info.value)


def test_truncated_binary_file_is_reported_with_sizes(tmp_path):
    data = write_inria_ply(tmp_path / "full.ply", random_attributes(3, 0), inria_property_names(0))
    (tmp_path / "cut.ply").write_bytes(data[:-10])
    with pytest.raises(InputError, match=r"cut.ply: truncated: .* 3 vertices of 68 bytes \(204 bytes\) but only 194"):
        load_ply(tmp_path / "cut.ply")


def test_missing_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="nothere.ply: cannot read"):
        load_ply(tmp_path / "nothere.ply")


def test_failed_save_leaves_no_file(tmp_path):
    g = Gaussians.from_activated(
        torch.zeros(1, 3),
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.ones(1, 3),
        torch.full((1,), 0.5),
        colors=torch.zeros(1, 4),
    )
    with pytest.raises(InputError, match="4 colour channels"):
        save_ply(tmp_path / "x.ply", g)
    assert list(tmp_path.iterdir()) == []


def test_feature_names_that_clash_with_3dgs_attributes_are_rejected(tmp_path):
    g = load_ply(_bad_file(tmp_path))
    g.features, g.feature_names = torch.zeros(4, 1), ("opacity",)
    with pytest.raises(InputError, match="feature names opacity clash"):
        save_ply(tmp_path / "clash.ply", g)


def test_empty_file_round_trips(tmp_path):
    g = load_ply(_bad_file(tmp_path)).select(torch.zeros(4, dtype=torch.bool))
    save_ply(tmp_path / "empty.ply", g)
    back = load_ply(tmp_path / "empty.ply")
    assert len(back) == 0 and back.sh_degree == 0
