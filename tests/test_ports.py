"""Ports: distributed loads have the requested resultant and zero moment; sensors
are their adjoints; bad port definitions are refused."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import build_model
from pipeline.config import Port, Ports, config_from_dict
from pipeline.errors import ConfigError, RegionError
from pipeline.fe.ports import port_matrices


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("ports"), size=0.02)


def resultants(space, column, point):
    f = column.reshape(-1, 3)
    r = space.node_points - point
    return f.sum(0), np.cross(r, f).sum(0)


def test_force_has_resultant_and_zero_moment_about_centroid(model):
    d = np.array([0.3, -1.0, 0.2])
    pm = port_matrices(model.space, model.regions,
                       Ports(inputs=(Port("f", "tip", "force", tuple(d)),)))
    force, moment = resultants(model.space, pm.F.toarray()[:, 0], [0.5, 0.01, 0.025])
    np.testing.assert_allclose(force, d / np.linalg.norm(d), atol=1e-13)
    np.testing.assert_allclose(moment, 0.0, atol=1e-14)


def test_moment_has_zero_resultant_and_requested_moment(model):
    pm = port_matrices(model.space, model.regions,
                       Ports(inputs=(Port("m", "tip", "moment", (1.0, 0.0, 0.0)),)))
    force, moment = resultants(model.space, pm.F.toarray()[:, 0], [0.5, 0.01, 0.025])
    np.testing.assert_allclose(force, 0.0, atol=1e-10)
    np.testing.assert_allclose(moment, [1.0, 0.0, 0.0], atol=1e-10)


def test_sensors_read_rigid_motions_exactly(model):
    ports = Ports(outputs=(Port("y", "tip", "displacement", (0.0, 1.0, 0.0)),
                           Port("rx", "tip", "rotation", (1.0, 0.0, 0.0))))
    pm = port_matrices(model.space, model.regions, ports)
    x = model.space.node_points
    translation = np.tile([0.0, 2e-3, 0.0], (x.shape[0], 1))
    theta = np.array([1e-3, 0.0, 0.0])
    rotation = np.cross(theta, x - [0.5, 0.01, 0.025])
    np.testing.assert_allclose(pm.T @ translation.ravel(), [2e-3, 0.0], atol=1e-15)
    np.testing.assert_allclose(pm.T @ rotation.ravel(), [0.0, 1e-3], atol=1e-15)
    assert pm.output_units == ("m", "rad")


def test_missing_region_is_refused(model):
    with pytest.raises(RegionError, match="ports.inputs\\[0\\].region.*'nowhere'"):
        port_matrices(model.space, model.regions,
                      Ports(inputs=(Port("f", "nowhere", "force", (0.0, 1.0, 0.0)),)))


BASE = {"name": "t", "geometry": {"kind": "box", "length": 0.5, "height": 0.02, "depth": 0.05},
        "mesh": {"size": 0.01}, "material": {"E": 69e9, "nu": 0.33, "rho": 2700.0}}


@pytest.mark.parametrize("ports, message", [
    ({"inputs": [{"name": "a", "region": "tip", "kind": "force", "direction": [0, 0, 0]}]},
     "ports.inputs\\[0\\].direction.*non-zero"),
    ({"inputs": [{"name": "a", "region": "tip", "kind": "force", "direction": [0, 1, 0]}],
      "outputs": [{"name": "a", "region": "tip", "kind": "displacement", "direction": [0, 1, 0]}]},
     "ports.outputs\\[0\\].name.*not used already"),
    ({"inputs": [{"name": "a", "region": "nowhere", "kind": "force", "direction": [0, 1, 0]}]},
     "ports.inputs\\[0\\].region.*'nowhere'"),
    ({"inputs": [{"name": "a", "region": "tip", "kind": "torque", "direction": [0, 1, 0]}]},
     "ports.inputs\\[0\\].kind.*force \\| moment"),
])
def test_bad_ports_are_refused_at_load(ports, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict({**BASE, "ports": ports})


def test_empty_selector_region_is_refused(model):
    from pipeline.config import RegionSelector
    from pipeline.fe.regions import resolve_regions

    far = {"patch": RegionSelector("sphere", point=(5.0, 5.0, 5.0), radius=0.01)}
    with pytest.raises(RegionError, match="regions.patch.*matches no boundary facet"):
        resolve_regions(model.space, far)
    plane = {"mid": RegionSelector("plane", point=(0.0, 0.02, 0.0), normal=(0.0, 1.0, 0.0))}
    tris = resolve_regions(model.space, plane)["mid"]
    np.testing.assert_allclose(model.space.body.vertices[tris][..., 1], 0.02)
