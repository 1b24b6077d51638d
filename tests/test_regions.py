"""clflow.regions.Region: the one region type of the config, the selection and the force stages."""

import pytest
import torch

from clflow.errors import InputError
from clflow.regions import Region


def test_box_selects_inside_and_its_boundary():
    box = Region.box((0.0, 0.0, 0.0), (1.0, 2.0, 1.0))
    points = torch.tensor(
        [
            [0.5, 1.0, 0.5],  # inside
            [0.0, 0.0, 0.0],  # the lower corner
            [1.0, 2.0, 1.0],  # the upper corner
            [1.0, 0.5, 0.5],  # on a face
            [1.0 + 1e-9, 0.5, 0.5],  # just past the face
            [0.5, -1e-9, 0.5],  # just below
            [0.5, 1.0, 3.0],  # far out
        ],
        dtype=torch.float64,
    )
    mask = box.select(points)
    assert mask.dtype == torch.bool
    assert mask.tolist() == [True, True, True, True, False, False, False]


def test_sphere_selects_within_the_radius_boundary_included():
    sphere = Region.sphere((1.0, 0.0, 0.0), 0.5)
    points = torch.tensor(
        [
            [1.0, 0.0, 0.0],  # the centre
            [1.5, 0.0, 0.0],  # on the surface
            [1.0, -0.5, 0.0],  # on the surface
            [1.0, 0.0, 0.5 + 1e-9],  # just outside
            [1.3, 0.3, 0.3],  # outside the sphere, inside its bounding box
        ],
        dtype=torch.float64,
    )
    assert sphere.select(points).tolist() == [True, True, True, False, False]


def test_bounds_are_compared_in_the_points_dtype():
    """A float32 point on a float32-rounded bound is inside (the simulator selects this way)."""
    box = Region.box((0.0, 0.0, 0.0), (0.1, 0.1, 0.1))
    point = torch.tensor([[0.1, 0.1, 0.1]], dtype=torch.float32)  # float32(0.1) = 0.10000000149 > 0.1
    assert box.select(point).tolist() == [True]
    assert box.select(point.double()).tolist() == [False]


def test_all_selects_everything():
    points = torch.randn(7, 3)
    assert Region("all").select(points).tolist() == [True] * 7
    assert Region("all").select(torch.zeros(0, 3)).shape == (0,)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Region("cube"), "region kind 'cube' unknown"),
        (lambda: Region.box((0, 0, 1), (1, 1, 0)), "is not below upper"),
        (lambda: Region.box((0, 0), (1, 1, 1)), "region lower must be 3 finite numbers"),
        (lambda: Region.sphere((0, 0, float("nan")), 1.0), "region center must be 3 finite numbers"),
        (lambda: Region.sphere((0, 0, 0), -1.0), "radius must be a finite number >= 0"),
    ],
)
def test_bad_regions_are_input_errors(make, message):
    with pytest.raises(InputError, match=message):
        make()


def test_regions_are_values():
    """Frozen, compared and hashed by value, their vectors stored as float tuples."""
    a = Region.box([0, 0, 0], [1, 1, 1])
    b = Region("box", lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0))
    assert a == b and hash(a) == hash(b) and a != Region.box((0, 0, 0), (1, 1, 2))
    assert a.lower == (0.0, 0.0, 0.0) and isinstance(a.upper[0], float)
