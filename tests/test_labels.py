"""Mode labels of bodies that are not beams: the rigid motion a mode resembles most, by
its effective mass share (pipeline.solve.labels)."""

from __future__ import annotations

import numpy as np

from pipeline.solve.labels import effective_mass_shares, label_modes, principal_frame


def _stocky_points(n=None, seed=0):
    """A 60 x 50 x 40 mm block: a regular grid of points (principal axes x, y, z), or
    ``n`` random points."""
    if n is not None:
        return np.random.default_rng(seed).uniform(0, 1, size=(n, 3)) * [0.06, 0.05, 0.04]
    g = np.meshgrid(np.linspace(0, 0.06, 7), np.linspace(0, 0.05, 6), np.linspace(0, 0.04, 5),
                    indexing="ij")
    return np.stack([a.ravel() for a in g], axis=1)


def test_stocky_body_modes_are_named_by_the_rigid_motion_they_resemble():
    x = _stocky_points()
    rng = np.random.default_rng(1)
    c = x.mean(axis=0)
    sway_y = np.tile([0.0, 1.0, 0.0], (len(x), 1)) + 0.05 * rng.standard_normal(x.shape)
    twist_z = np.cross([0.0, 0.0, 1.0], x - c) * 40 + 0.05 * rng.standard_normal(x.shape)
    # an internal mode: orthogonal (with unit weights) to all six rigid motions
    shares_probe = rng.standard_normal(x.shape)
    rigid = [np.tile(e, (len(x), 1)) for e in np.eye(3)]
    rigid += [np.cross(e, x - c) for e in np.eye(3)]
    R = np.stack([r.ravel() for r in rigid], axis=1)
    v = shares_probe.ravel()
    v -= R @ np.linalg.lstsq(R, v, rcond=None)[0]
    internal = v.reshape(x.shape)
    shapes = np.stack([sway_y, twist_z, internal, 2 * sway_y], axis=2)
    labels = label_modes(x, shapes, 0)
    assert labels == ["translation_y_1", "rotation_z_1", "internal_1", "translation_y_2"]


def test_effective_mass_shares_of_a_complete_basis_sum_to_one():
    # with the modes a complete weight-orthonormal basis, the effective masses of every
    # rigid direction add up to the whole mass (inertia): share sums are 1 (to round-off)
    x = _stocky_points(n=20, seed=3)
    w = np.random.default_rng(4).uniform(0.5, 2.0, size=20)
    Q, _ = np.linalg.qr(np.random.default_rng(5).standard_normal((60, 60)))
    # phi^T W phi = I with W = diag(w per DOF): phi = W^-1/2 Q
    phi = Q / np.sqrt(np.repeat(w, 3))[:, None]
    shares, names = effective_mass_shares(x, phi.reshape(20, 3, 60), w)
    np.testing.assert_allclose(shares.sum(axis=1), np.ones(6), atol=1e-12)
    assert len(names) == 3


def test_principal_axes_name_the_global_axis_they_align_with():
    x = _stocky_points()
    _, axes, names = principal_frame(x, np.ones(len(x)))
    assert sorted(names) == ["x", "y", "z"]
    # rotated by 40 degrees about z: the in-plane axes are no global axis any more
    t = np.radians(40)
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    _, _, names = principal_frame(x @ rot.T, np.ones(len(x)))
    assert "z" in names and sum(n.startswith("p") for n in names) == 2


def _labels_over_shares(x, w, shapes, n_rigid, shares):
    """label_modes evaluated on disjoint ``shares`` of the points (index arrays) as the
    ranks of the distributed path evaluate it: the body's frame from every point, each
    share's sums added (an emulated MPI_Allreduce: every share is evaluated once to
    collect its sums, then the totals are handed out in the same order)."""
    from pipeline.solve.labels import label_frame

    frame = label_frame(x, w)
    collected = []
    for idx in shares:
        sums = []
        label_modes(x[idx], shapes[idx], n_rigid, w[idx], frame=frame,
                    reduce_sum=lambda a, sums=sums: sums.append(a) or a)
        collected.append(sums)
    totals = iter([sum(parts) for parts in zip(*collected)])
    return [label_modes(x[idx], shapes[idx], n_rigid, w[idx], frame=frame,
                        reduce_sum=lambda a: next(totals)) for idx in shares[:1]][0]


def test_labels_from_shares_of_the_points_are_the_whole_bodys():
    """The distributed path's labels: each share of the points (a rank's) sums over its
    own points, the body's geometry (LabelFrame) made once from every point; a beam-like
    and a stocky body give the labels of the whole point set. Each share's modes are
    random fields here, so the labels test the sums, not a physical classification."""
    rng = np.random.default_rng(7)
    for extent in ([0.5, 0.02, 0.05], [0.06, 0.05, 0.04]):
        x = rng.uniform(0, 1, size=(900, 3)) * extent
        w = rng.uniform(0.5, 2.0, size=900)
        shapes = rng.standard_normal((900, 3, 8))
        whole = label_modes(x, shapes, 1, w)
        shares = np.array_split(rng.permutation(900), 3)
        assert _labels_over_shares(x, w, shapes, 1, shares) == whole
