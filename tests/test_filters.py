"""Tests of pipeline.reduce.filters on a fixed-free spring-mass chain reduced by pipeline.reduce.modal.

The chain (6 masses of 1 kg, springs 1e4 N/m, fixed at one end) is reduced to its 3
lowest modes (3.8, 11.3, 18.1 Hz); two force inputs and two displacement outputs, residual
static correction
so the plant has a non-zero D on its position rows as well as on its accelerations.
python-control serves as the independent evaluator (series connection, DC gain,
forced response).
"""

from __future__ import annotations

import logging
import math

import control as ct
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp

from pipeline.errors import ConfigError
from pipeline.store.schema import filter_datasets, filter_group_attrs
from pipeline.reduce.filters import (
    filtered_model,
    first_order_filter,
    third_order_position_filter,
)
from pipeline.reduce.modal import DampingSpec, reduce_model

N_MASS, K_SPRING = 6, 1e4
CUTOFF_HZ = 200.0  # > 5 x 18.1 Hz, the highest retained mode


@pytest.fixture(scope="module")
def plant():
    main = np.full(N_MASS, 2.0)
    main[-1] = 1.0
    K = sp.csr_matrix(K_SPRING * sp.diags([main, -np.ones(N_MASS - 1), -np.ones(N_MASS - 1)],
                                          [0, 1, -1]))
    M = sp.identity(N_MASS, format="csr")
    w2, Phi = sla.eigh(K.toarray(), M.toarray())
    F = np.zeros((N_MASS, 2))
    F[-1, 0], F[2, 1] = 1.0, 1.0
    T = sp.csr_matrix(np.eye(N_MASS)[[N_MASS - 1, 2]])
    return reduce_model(K, M, Phi, w2, F, T, 3, DampingSpec("uniform", ratio=0.05),
                        "residual", ["f_end", "f_mid"], ["x_end", "x_mid"])


def ss(m):
    return ct.ss(m.A, m.B, m.C, m.D)


def K_of(cutoff_hz=CUTOFF_HZ):
    return 2 * math.pi * cutoff_hz


# --------------------------------------------------------------------------- filters alone
def test_first_order_filter_alone():
    f = first_order_filter(3, K_of())
    A, B, C, D = f.A, f.B, f.C, f.D
    assert not np.any(D)
    assert np.allclose(ct.dcgain(ct.ss(A, B, C, D)), np.eye(3), rtol=1e-14, atol=1e-14)
    assert np.allclose(np.linalg.eigvals(A), -K_of(), rtol=1e-15)
    # H(s) = K / (s + K) at s = i K: 1 / (1 + i)
    H = ct.ss(A, B, C, D)(1j * K_of())
    assert np.allclose(H, np.eye(3) / (1 + 1j), rtol=1e-13)


def test_third_order_filter_alone():
    n, K = 2, K_of()
    f = third_order_position_filter(n, K)
    assert f.A.shape == (6, 6) and f.B.shape == (6, 2) and f.C.shape == (6, 6)
    assert not np.any(f.D)
    dc = ct.dcgain(ss(f))
    # unit DC gain on the positions, zero static velocity and acceleration
    assert np.allclose(dc, np.vstack([np.eye(n), np.zeros((2 * n, n))]), rtol=0, atol=1e-12)
    # the transfer functions K^3/(s+K)^3 times 1, s, s^2 at a few frequencies
    for s in (0.3j * K, 1j * K, 1.0 + 7j * K):
        H = ss(f)(s)
        base = K**3 / (s + K) ** 3
        for k, factor in enumerate((1, s, s * s)):
            assert np.allclose(H[k * n:(k + 1) * n], factor * base * np.eye(n), rtol=1e-12)
    with pytest.raises(ValueError):
        third_order_position_filter(1, 0.0)


# --------------------------------------------------------------------------- series
@pytest.mark.parametrize("kind", ["first_order", "third_order"])
def test_filtered_model_is_the_series_connection(plant, kind):
    p = plant.statespace
    assert np.any(p.D[:2]) and np.any(p.D[4:])  # residual and acceleration feedthrough
    f = filtered_model(plant, kind, CUTOFF_HZ)
    assert f.D.shape == p.D.shape and not np.any(f.D)
    assert f.output_names == p.output_names and f.input_names == p.input_names
    assert f.state_names[:p.n_states] == p.state_names
    assert f.filter_kind == kind and f.cutoff_hz == CUTOFF_HZ
    if kind == "first_order":
        ref = ct.series(ss(p), ss(first_order_filter(6, K_of())))
        assert f.state_names[p.n_states:] == tuple(f"filter/{o}" for o in p.output_names)
    else:
        pos = ct.ss(p.A, p.B, p.C[:2], p.D[:2])
        ref = ct.series(pos, ss(third_order_position_filter(2, K_of())))
        assert f.state_names[p.n_states:p.n_states + 3] == (
            "filter/x_end/w", "filter/x_end/w_dot", "filter/x_end/w_ddot")
    assert f.n_states == p.n_states + 6
    # python-control's series connection: same transfer matrix (round-off)
    for s in (1j, 10j, 100j, 1000j, 5.0 + 300j):
        assert np.allclose(ss(f)(s), ref(s), rtol=1e-10, atol=1e-12 * np.abs(ref(s)).max())
    # DC gain of the filtered model = DC gain of the plant (position = compliance)
    assert np.allclose(ct.dcgain(ss(f)), ct.dcgain(ss(p)), rtol=1e-10,
                       atol=1e-12 * np.abs(plant.static_compliance).max())
    assert np.allclose(ct.dcgain(ss(f))[:2], plant.static_compliance, rtol=1e-9)


@pytest.mark.parametrize("kind", ["first_order", "third_order"])
def test_filtered_poles_are_plant_poles_and_filter_poles(plant, kind):
    p = plant.statespace
    f = filtered_model(p, kind, CUTOFF_HZ)
    K = K_of()
    poles = np.linalg.eigvals(f.A)
    assert np.allclose(np.sort_complex(ss(f).poles()), np.sort_complex(poles), rtol=1e-12)
    plant_poles = np.linalg.eigvals(p.A)
    near_K = np.abs(poles + K) < 1e-3 * K
    assert np.count_nonzero(near_K) == 6  # 3 n_y (first order) or 3 per port (third order)
    for q in plant_poles:  # every plant pole survives, 1e-9 relative
        assert np.min(np.abs(poles[~near_K] - q)) < 1e-9 * abs(q)
    # -K is a multiple eigenvalue. For the third-order filter it is defective (Jordan
    # blocks of 3), so each computed copy is only good to ~eps^(1/3) ~ 6e-6 relative,
    # but the mean of the cluster is well-conditioned (round-off).
    cluster = poles[near_K]
    assert np.max(np.abs(cluster + K)) < 1e-4 * K
    assert abs(cluster.mean() + K) < 1e-9 * K


def test_third_order_outputs_are_consistent_derivatives(plant):
    f = filtered_model(plant, "third_order", CUTOFF_HZ)
    Cp, Cv, Ca = f.C[:2], f.C[2:4], f.C[4:]
    # exactly: v = d/dt p, a = d/dt v, with no feedthrough (C_v = C_p A, C_p B = 0, ...)
    assert np.allclose(Cv, Cp @ f.A, rtol=0, atol=1e-12 * np.abs(Cv).max())
    assert np.allclose(Ca, Cv @ f.A, rtol=0, atol=1e-12 * np.abs(Ca).max())
    assert np.abs(Cp @ f.B).max() < 1e-12 * np.abs(Cv).max()
    assert np.abs(Cv @ f.B).max() < 1e-12 * np.abs(Ca).max()


def test_simulated_velocity_and_acceleration_are_derivatives(plant):
    f = filtered_model(plant, "third_order", CUTOFF_HZ)
    # smooth input: a raised-cosine pulse on f_end, a delayed one on f_mid (C^1 in time)
    tau = 0.05
    t = np.linspace(0.0, 0.6, 60001)  # dt = 1e-5 s = 1/(126 K)

    def pulse(t0):
        x = np.clip((t - t0) / tau, 0.0, 1.0)
        return np.sin(np.pi * x) ** 2

    u = np.vstack([pulse(0.0), -0.5 * pulse(0.1)])
    y = ct.forced_response(ss(f), t, u).outputs
    for k in range(2):
        p, v, a = y[k], y[2 + k], y[4 + k]
        dp, dv = np.gradient(p, t), np.gradient(v, t)
        # forced_response is exact for the piecewise-linear input, so the only error is
        # the central difference's dt^2/6 |p'''| (|v'''| for a; one-sided at the ends,
        # skipped). Measured: 1e-7 of the peak for v, 1.2e-6 for a (a''' is the largest,
        # the filter passes the input's kinks in u'' through its K-fast dynamics).
        # 2e-5 is ~15x that, and 1000x below the inconsistency of the unfiltered plant
        # (3.7e-2, last assertion).
        inner = slice(1, -1)
        assert np.max(np.abs(dp - v)[inner]) < 2e-5 * np.max(np.abs(v))
        assert np.max(np.abs(dv - a)[inner]) < 2e-5 * np.max(np.abs(a))
    # the unfiltered residual-corrected plant is NOT consistent (this is what the
    # third-order filter is for): its velocity misses d/dt of the residual term
    yp = ct.forced_response(ss(plant.statespace), t, u).outputs
    mismatch = np.max(np.abs(np.gradient(yp[0], t) - yp[2])) / np.max(np.abs(yp[2]))
    assert mismatch > 1e-2


def test_first_order_filters_every_output_alike(plant):
    # every output of the plant passes through the same K/(s+K)
    f = filtered_model(plant, "first_order", CUTOFF_HZ)
    p = plant.statespace
    H = 1 / (1 + 30j / K_of())
    assert np.allclose(ss(f)(30j), H * ss(p)(30j), rtol=1e-10)


# --------------------------------------------------------------------------- config
def test_cutoff_must_be_positive(plant):
    for bad in (0.0, -10.0, float("nan"), None, "2000"):
        with pytest.raises(ConfigError, match=r"filter\.cutoff_hz"):
            filtered_model(plant, "third_order", bad)
    with pytest.raises(ConfigError, match=r"filter\.kind"):
        filtered_model(plant, "fourth_order", 100.0)
    assert filtered_model(plant, "none", None) is plant.statespace


def test_low_cutoff_warns(plant, caplog):
    f_max = plant.statespace.frequencies_hz.max()
    with caplog.at_level(logging.WARNING, logger="pipeline.reduce.filters"):
        filtered_model(plant, "third_order", 5.0 * f_max * 1.01)
    assert not caplog.records
    with caplog.at_level(logging.WARNING, logger="pipeline.reduce.filters"):
        filtered_model(plant, "first_order", 4.0 * f_max)
    assert any("filter.cutoff_hz" in r.message for r in caplog.records)


def test_filter_datasets(plant):
    tree = filter_datasets(plant, "third_order", CUTOFF_HZ)
    f = filtered_model(plant, "third_order", CUTOFF_HZ)
    for k in "ABCD":
        d = tree[f"statespace_filtered/{k}"]
        assert np.array_equal(d.data, getattr(f, k))
        assert d.attrs["filter_kind"] == "third_order" and d.attrs["cutoff_hz"] == CUTOFF_HZ
    assert float(tree["statespace_filtered/cutoff_hz"].data) == CUTOFF_HZ
    assert tree["statespace_filtered/cutoff_hz"].units == "Hz"
    assert list(tree["statespace_filtered/state_names"].data) == list(f.state_names)
    assert list(tree["statespace_filtered/output_names"].data) == list(f.output_names)
    # an already filtered model is accepted when kind and cutoff match
    again = filter_datasets(f, "third_order", CUTOFF_HZ)
    assert np.array_equal(again["statespace_filtered/A"].data, f.A)
    with pytest.raises(ValueError):
        filter_datasets(f, "first_order", CUTOFF_HZ)
    none = filter_datasets(plant, "none", None)
    assert np.isnan(float(none["statespace_filtered/cutoff_hz"].data))
    assert filter_group_attrs("first_order", 1e3) == {
        "statespace_filtered": {"filter_kind": "first_order", "cutoff_hz": 1e3}}
