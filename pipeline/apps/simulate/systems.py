"""Model algebra: the state-space systems a scenario steps, built from the file's models.

Every elastic model is the one :class:`~pipeline.reduce.statespace.StateSpace` type
(force inputs in N, ``<port>/position|velocity|acceleration`` outputs in m, m/s, m/s^2).
This module derives new ones from the file's plant (SI units throughout):

- :func:`undamped`: the modal plant without its modal damping (A[eta_dot, eta_dot] = 0);
- :func:`refilter`: the plant in series with a position/output filter at another cutoff
  (theory.md §4);
- :func:`filtered_for` / :func:`lumped_for`: the FE model or lumped chain a scenario uses;
- :func:`step_system`: one force input -> one port's motion;
- :func:`coupled_system`: a rigid mass welded to a port (the algebraic loop broken by a
  filtered model or solved exactly), optionally on a revolute spring :class:`Mount`.

Each system to step is a :class:`SteppedSystem`: a StateSpace ``z' = A z + B w,
signals = C z + D w`` (``w`` piecewise-constant external inputs; C and D are also called
S and Sw below) plus the modal state indices the elastic energy needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.errors import ConfigError, FileFormatError, SolverError
from pipeline.reduce.filters import (CUTOFF_MARGIN, first_order_filter,
                                     third_order_position_filter)
from pipeline.reduce.statespace import StateSpace
from pipeline.store.read import ModelFile

from pipeline.apps.simulate.scenarios import Scenario

__all__ = ["CONSISTENCY_TOL", "rel_close", "derived_rows", "undamped", "fe_band_hz",
           "refilter", "filtered_for", "lumped_for", "SteppedSystem", "step_system", "Mount",
           "coupled_system", "directions", "mount_for"]

#: Relative tolerance of the checks that a file's outputs are consistent (velocity and
#: acceleration rows equal to the derivatives of the position row through A and B).
CONSISTENCY_TOL = 1e-8


def rel_close(a: np.ndarray, b: np.ndarray, tol: float = CONSISTENCY_TOL) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(float(np.abs(a).max(initial=0.0)), float(np.abs(b).max(initial=0.0)), 1e-300)
    return float(np.abs(a - b).max(initial=0.0)) <= tol * scale


def derived_rows(em: StateSpace, port: str, j: int, check: bool) -> dict[str, Any]:
    """Position row of ``port`` and its derivatives through A and B.

    Y = cp x + dp u;  Y' = cp A x + cp b u (+ dp u');  Y'' = cp A^2 x + cp A b u + dp u''
    when cp b = 0 (true for every model of theory.md §3). With ``check``, the file's
    velocity/acceleration rows must equal these (the exact coupling relies on it).
    """
    ip, iv, ia = em.rows(port)
    A, b = em.A, em.B[:, j]
    cp, dp = em.C[ip], float(em.D[ip, j])
    cv, ca = cp @ A, cp @ A @ A
    dv, da = float(cp @ b), float(cp @ A @ b)
    scale = max(float(np.abs(cv).max()), 1e-300) * max(float(np.abs(b).max()), 1e-300)
    if abs(dv) > CONSISTENCY_TOL * scale:
        raise FileFormatError(f"{em.label} model: the position of port '{port}' responds "
                              f"directly to input rate (C_pos B = {dv:.3g} != 0), so the "
                              "exact mass coupling is not defined; use loop: filtered")
    if check:
        file_ok = (rel_close(em.C[iv], cv) and rel_close(em.C[ia], ca)
                   and abs(em.D[iv, j]) <= CONSISTENCY_TOL * max(abs(da), 1e-300)
                   and rel_close(np.array([em.D[ia, j]]), np.array([da])))
        if not file_ok:
            raise FileFormatError(f"{em.label} model: the velocity/acceleration outputs of port "
                                  f"'{port}' are not the derivatives of its position output "
                                  "through A and B; the file is inconsistent")
    return dict(cp=cp, cv=cv, ca=ca, dp=dp, dv=0.0, da=da)


def undamped(em: StateSpace, max_hz: float | None = None) -> StateSpace:
    """The modal model with its damping removed: A[eta_dot_k, eta_dot_k] = 0 for every mode
    with omega_k <= 2 pi ``max_hz`` (all modes when None), and the velocity and
    acceleration rows re-derived from the position rows through the new A (the file's rows
    are first checked to be those derivatives). ConfigError if the model is not modal."""
    idx = em.modal_indices()
    if idx is None:
        raise ConfigError(f"damping: false needs a modal model (states eta_k, eta_dot_k with "
                          f"diagonal blocks); the {em.label} model is not one",
                          key="damping", value=False, expected="a modal model")
    e, d = idx
    A = em.A.copy()
    omega = np.sqrt(np.maximum(-np.diag(em.A[np.ix_(d, e)]), 0.0))
    keep = d if max_hz is None else d[omega <= 2 * math.pi * max_hz * (1 + 1e-9)]
    A[keep, keep] = 0.0
    C, D = em.C.copy(), em.D.copy()
    for port in em.ports:
        ip, iv, ia = em.rows(port)
        for j in range(len(em.input_names)):
            derived_rows(em, port, j, check=True)
        C[iv] = em.C[ip] @ A
        C[ia] = em.C[ip] @ A @ A
        D[iv] = em.C[ip] @ em.B
        D[ia] = em.C[ip] @ A @ em.B
    return replace(em, A=A, C=C, D=D)


def fe_band_hz(mf: ModelFile) -> float:
    """Highest mode frequency of the FE plant (Hz): the band the FE and lumped models share."""
    idx = mf.plant.modal_indices()
    if idx is None:
        return float(np.max(np.abs(mf.plant.poles()))) / (2 * math.pi)
    e, d = idx
    return float(np.sqrt(np.max(-np.diag(mf.plant.A[np.ix_(d, e)])))) / (2 * math.pi)


def refilter(plant: StateSpace, kind: str, cutoff_hz: float) -> StateSpace:
    """filter * plant with pipeline.reduce.filters' realisation (theory.md §4), D = 0."""
    K = 2.0 * math.pi * float(cutoff_hz)
    ports = plant.ports
    if kind == "third_order":
        rows = [plant.rows(p)[0] for p in ports]
        Af, Bf, Cf, Df = third_order_position_filter(len(ports), K)
        order = [plant.output_names.index(f"{p}/{q}") for q in
                 ("position", "velocity", "acceleration") for p in ports]
        extra = tuple(f"filter/{p}/{s}" for p in ports for s in ("w", "w_dot", "w_ddot"))
    elif kind == "first_order":
        rows = list(range(len(plant.output_names)))
        Af, Bf, Cf, Df = first_order_filter(len(rows), K)
        order = rows
        extra = tuple(f"filter/{n}" for n in plant.output_names)
    else:
        raise FileFormatError(f"filtered model of kind {kind!r} is not known to the stepper")
    Cp, Dp = plant.C[rows], plant.D[rows]
    n, nf = plant.A.shape[0], Af.shape[0]
    A = np.block([[plant.A, np.zeros((n, nf))], [Bf @ Cp, Af]])
    B = np.vstack([plant.B, Bf @ Dp])
    Cfull = np.hstack([Df @ Cp, Cf])
    C = np.zeros_like(Cfull)
    C[order] = Cfull  # filter outputs are ordered like the plant's
    D = np.zeros((C.shape[0], plant.B.shape[1]))
    return StateSpace(A, B, C, D, plant.input_names, plant.output_names,
                      plant.state_names + extra,
                      label=f"FE filtered ({kind.replace('_', '-')} {cutoff_hz:g} Hz)",
                      filter_kind=kind, cutoff_hz=float(cutoff_hz))


def filtered_for(mf: ModelFile, sc: Scenario, notes: list[str]) -> StateSpace:
    """The filtered model a ``loop: filtered`` scenario steps (file's, or re-filtered)."""
    if mf.filtered is None:
        raise FileFormatError(
            f"file '{mf.path}': has no filtered model (/statespace_filtered; the config's "
            f"filter.kind was none), which scenario '{sc.name}' needs for loop: filtered; set "
            "loop: exact in the scenario, or rebuild the file with a filter")
    fk, fc = mf.filtered.filter_kind, mf.filtered.cutoff_hz
    if fc is None or not math.isfinite(fc):
        raise FileFormatError(f"file '{mf.path}': the filtered model has no cutoff_hz")
    rebuilt = refilter(mf.plant, fk, fc)
    same = all(rel_close(getattr(rebuilt, k), getattr(mf.filtered, k), 1e-9) for k in "ABCD")
    if not same:
        raise FileFormatError(f"file '{mf.path}': /statespace_filtered is not the plant in "
                              f"series with a {fk} filter at {fc:g} Hz as its attributes say")
    cutoff = fc if sc.cutoff_hz is None else sc.cutoff_hz
    plant = mf.plant if sc.damping else undamped(mf.plant)
    model = mf.filtered if (sc.damping and sc.cutoff_hz is None) else refilter(plant, fk, cutoff)
    model = replace(model, label=f"FE filtered ({fk.replace('_', '-')} {cutoff:g} Hz)")
    f_max = float(mf.plant.n_states and np.max(np.abs(mf.plant.poles()))) / (
        2 * math.pi)
    if cutoff < CUTOFF_MARGIN * f_max:
        notes.append(f"cutoff {cutoff:g} Hz is below {CUTOFF_MARGIN:g} x the highest mode "
                     f"({f_max:.4g} Hz): the filter distorts the dynamics")
    return model


def lumped_for(mf: ModelFile, sc: Scenario, inp: str, port: str
               ) -> tuple[StateSpace | None, str]:
    """The lumped chain with its ports renamed to the FE ports, or (None, why not)."""
    lp = mf.lumped
    if lp is None:
        return None, "the file has no lumped model"
    if not sc.lumped:
        return None, "lumped: false"
    pin, pout = mf.ports.get(inp), mf.ports.get(port)
    if pin is None or pout is None or pin["direction"] is None or pout["direction"] is None:
        return None, "the file does not record the port directions"
    if pin["region"] != "tip" or pout["region"] != "tip":
        return None, (f"the ports are on regions '{pin['region']}'/'{pout['region']}', the "
                      "lumped chain only has the tip")
    if not (np.allclose(pin["direction"], lp["input_direction"], atol=1e-9)
            and np.allclose(pout["direction"], lp["output_direction"], atol=1e-9)):
        return None, "the lumped chain's tip force/displacement directions differ from the ports"
    if len(lp["input_names"]) != 1 or len(lp["output_names"]) != 3:
        return None, "the lumped model is not a single tip force -> tip motion model"
    em = StateSpace(lp["A"], lp["B"], lp["C"], lp["D"], (inp,),
                    tuple(f"{port}/{q}" for q in ("position", "velocity", "acceleration")),
                    lp["state_names"], label="lumped")
    if not sc.damping:
        band = fe_band_hz(mf)
        em = undamped(em, band)
        idx = em.modal_indices()
        if idx is not None:
            e, d = idx
            w = np.sqrt(np.maximum(-np.diag(lp["A"][np.ix_(d, e)]), 0.0)) / (2 * math.pi)
            excited = (np.abs(lp["B"][d, 0]) > 0) & (w > band * (1 + 1e-9))
            if excited.any():
                return em, (f"lumped chain: damping removed from its modes up to {band:.4g} Hz "
                            f"(the FE model's band); its {int(excited.sum())} higher excited "
                            "modes keep their damping (as an integrator's numerical "
                            "dissipation would)")
    return em, ""


# =========================================================================== LTI systems
@dataclass(frozen=True, eq=False)
class SteppedSystem:
    """z' = A z + B w, signals = S z + Sw w (w piecewise constant): a StateSpace whose
    outputs are the recorded signals (with their units) and whose inputs are the external
    inputs w, plus ``modal``: the (eta, eta_dot) state indices of the undamped-energy
    measure, or None (they are not recoverable from the coupled A, whose blocks the mass
    couples)."""

    model: StateSpace
    modal: tuple[np.ndarray, np.ndarray] | None = None

    # aliases in the notation of the stepper: z' = A z + B w, signals = S z + Sw w
    A = property(lambda self: self.model.A)
    B = property(lambda self: self.model.B)
    S = property(lambda self: self.model.C)
    Sw = property(lambda self: self.model.D)
    signals = property(lambda self: self.model.output_names)
    units = property(lambda self: self.model.output_units)

    def equilibrium(self, w: np.ndarray) -> np.ndarray:
        """Steady state z with constant inputs w: -A^-1 B w. SolverError (one line) when A
        is singular or nearly so: a stiffness or mass of ~0 leaves no static equilibrium."""
        bw = self.B @ w
        scale = float(np.abs(bw).max(initial=0.0))
        if scale == 0.0:
            return np.zeros(self.A.shape[0])
        bw = bw / scale  # linear: solved for a unit load (a 1e-320 N load is no subnormal)
        try:
            z = np.linalg.solve(self.A, bw)
        except np.linalg.LinAlgError:
            z = np.full(self.A.shape[0], np.nan)
        with np.errstate(all="ignore"):  # the residual of a singular solve may overflow
            resid = float(np.abs(self.A @ z - bw).max(initial=0.0))
        if not (np.all(np.isfinite(z)) and resid <= 1e-6):
            raise SolverError("scenario: the coupled system has no static equilibrium (its A "
                              "is singular to double precision: a stiffness, mass or cutoff "
                              "far from the body's own); use values of the order of the "
                              "body's own")
        return -z * scale

    def signal(self, name: str) -> int:
        return self.signals.index(name)


def step_system(em: StateSpace, inp: str, port: str) -> SteppedSystem:
    j = em.col(inp)
    ip, iv, ia = em.rows(port)
    rows = [ip, iv, ia]
    S = np.vstack([em.C[rows], np.zeros((1, em.A.shape[0]))])
    Sw = np.vstack([em.D[rows, j:j + 1], [[1.0]]])
    model = StateSpace(em.A, em.B[:, j:j + 1], S, Sw, ("force",),
                       (f"{port}/position", f"{port}/velocity", f"{port}/acceleration", inp),
                       em.state_names, output_units=("m", "m/s", "m/s^2", "N"),
                       label=em.label)
    return SteppedSystem(model, em.modal_indices())


@dataclass(frozen=True)
class Mount:
    """Revolute joint about z: stiffness k (N m/rad), damping c (N m s/rad), the body's
    inertia J about the joint axis (kg m^2), c_theta = (e_z x r_port)·d_out (m, the port's
    displacement along d_out per radian), M_g: gravity moment on the body (N m) per unit
    gravity vector, handled through w."""

    k: float
    c: float
    J: float
    c_theta: float
    arm: np.ndarray
    joint: np.ndarray


def coupled_system(em: StateSpace, inp: str, port: str, mass: float, s_io: float,
                    exact: bool, mount: Mount | None) -> tuple[SteppedSystem, str]:
    """The elastic model with a rigid mass on ``port`` (and the revolute mount).

    External constant inputs w = [g_out (m/s^2, gravity along d_out), M_g (N m, gravity
    moment on the body about the joint), P (N, preload on the input port)].

    Equations (f: force the mass exerts on the body along d_out; u: the input, along d_in
    = s_io d_out; Y: the port's displacement in the body frame; theta: joint angle):

        u - s_io f = P
        f + m (c_theta theta'' + Y'') = m g_out,   Y'' = ca x + da u + dp u''
        J theta'' + c theta' + k theta = c_theta s_io u + M_g
        x' = A x + b u

    ``exact`` with a position feedthrough dp != 0 (residual flexibility): u becomes a state
    (the residual spring between the modal body and the mass); otherwise u, f and theta''
    are solved from the first three equations (the algebraic loop, solved exactly), or for
    a filtered model (D = 0) they are explicit.
    """
    j = em.col(inp)
    nx = em.A.shape[0]
    A, b = em.A, em.B[:, j]
    if exact:
        r = derived_rows(em, port, j, check=True)
        cp, cv, ca, dp, dv, da = (r[k] for k in ("cp", "cv", "ca", "dp", "dv", "da"))
    else:
        ip, iv, ia = em.rows(port)
        cp, cv, ca = em.C[ip], em.C[iv], em.C[ia]
        dp, dv, da = float(em.D[ip, j]), float(em.D[iv, j]), float(em.D[ia, j])
        if max(abs(dp), abs(dv), abs(da)) > 0.0:
            raise FileFormatError(f"{em.label}: the filtered model has D != 0 for port "
                                  f"'{port}', so it does not break the loop")
    m = float(mass)
    residual = exact and m > 0.0 and dp != 0.0
    how = ("exact loop, residual flexibility as a spring state" if residual else
           "exact loop (algebraic, solved in closed form)" if exact else
           "filtered model (no algebraic loop)")
    if residual and s_io * dp <= 0.0:
        raise FileFormatError(f"{em.label}: the residual flexibility {dp:.3g} has the sign of "
                              "a negative compliance for these collocated ports")
    names = list(em.state_names)
    it = ithd = iu = iud = -1
    nz = nx
    if mount is not None:
        it, ithd = nz, nz + 1
        nz += 2
        names += ["theta", "theta_dot"]
    if residual:
        iu, iud = nz, nz + 1
        nz += 2
        names += ["u", "u_dot"]
    nq = 3 if mount is not None else 2          # q = [u or u'', f, theta'']
    Eq, Ez, Ew = np.zeros((nq, nq)), np.zeros((nq, nz)), np.zeros((nq, 3))
    # E1: u - s f = P
    Eq[0, 1] = -s_io
    Ew[0, 2] = 1.0
    if residual:
        Ez[0, iu] = -1.0
    else:
        Eq[0, 0] = 1.0
    # E2: f + m (c_theta theta'' + ca x + da u + dp u'') = m g_out
    Eq[1, 1] = 1.0
    Ez[1, :nx] = -m * ca
    Ew[1, 0] = m
    if residual:
        Eq[1, 0] = m * dp
        Ez[1, iu] += -m * da
    else:
        Eq[1, 0] = m * da
    if mount is not None:
        Eq[1, 2] = m * mount.c_theta
        # E3: J theta'' - c_theta s u = -k theta - c theta_dot + M_g
        Eq[2, 2] = mount.J
        Ez[2, it], Ez[2, ithd] = -mount.k, -mount.c
        Ew[2, 1] = 1.0
        if residual:
            Ez[2, iu] += mount.c_theta * s_io
        else:
            Eq[2, 0] = -mount.c_theta * s_io
    if not exact or not residual:
        loop = 1.0 + s_io * m * da
        if loop <= 1e-12:
            raise ConfigError(f"the mass loop on ports '{inp}'/'{port}' is ill-posed "
                              f"(1 + s m D_acc = {loop:.3g} <= 0): the input and output ports "
                              "must be collocated (same point, parallel directions)",
                              key=f"{inp}/{port}", value=loop,
                              expected="collocated ports (1 + s m D_acc > 0)")
    Qz, Qw = np.linalg.solve(Eq, Ez), np.linalg.solve(Eq, Ew)
    Dz, Dq = np.zeros((nz, nz)), np.zeros((nz, nq))
    Dz[:nx, :nx] = A
    if residual:
        Dz[:nx, iu] = b
        Dz[iu, iud] = 1.0
        Dq[iud, 0] = 1.0
    else:
        Dq[:nx, 0] = b
    if mount is not None:
        Dz[it, ithd] = 1.0
        Dq[ithd, 2] = 1.0
    Abar = Dz + Dq @ Qz
    Bbar = Dq @ Qw

    def row(x=None, z=None, q=None, w=None):
        """(S row, Sw row) of a signal given by its coefficients on the elastic states x,
        other states z, unknowns q and external inputs w."""
        sz, sq, sw = np.zeros(nz), np.zeros(nq), np.zeros(3)
        if x is not None:
            sz[:nx] += x
        for arr, spec in ((sz, z), (sq, q), (sw, w)):
            for k, v in (spec or {}).items():
                arr[k] += v
        return sz + sq @ Qz, sq @ Qw + sw

    u_row = row(z={iu: 1.0}) if residual else row(q={0: 1.0})
    if residual:
        pos = row(x=cp, z={iu: dp})
        vel = row(x=cv, z={iu: dv, iud: dp})
        acc = row(x=ca, z={iu: da}, q={0: dp})
    else:
        pos = row(x=cp, q={0: dp})
        vel = row(x=cv, q={0: dv})
        acc = row(x=ca, q={0: da})
    f_row = row(q={1: 1.0})
    sigs = [(f"{port}/position", "m", pos), (f"{port}/velocity", "m/s", vel),
            (f"{port}/acceleration", "m/s^2", acc), (inp, "N", u_row),
            ("mass_force", "N", f_row)]
    if mount is not None:
        th, thd = row(z={it: 1.0}), row(z={ithd: 1.0})
        tip = (th[0] * mount.c_theta + pos[0], th[1] * mount.c_theta + pos[1])
        sigs += [("theta", "rad", th), ("theta_dot", "rad/s", thd),
                 ("mass_displacement", "m", tip)]
    else:
        sigs += [("mass_displacement", "m", pos)]
    S = np.vstack([s[2][0] for s in sigs])
    Sw = np.vstack([s[2][1] for s in sigs])
    modal = em.modal_indices() if em.filter_kind == "none" else None
    model = StateSpace(Abar, Bbar, S, Sw, ("g_out", "M_g", "preload"),
                       tuple(s[0] for s in sigs), names, output_units=tuple(s[1] for s in sigs),
                       label=em.label)
    return SteppedSystem(model, modal), how


def directions(mf: ModelFile, sc: Scenario, inp: str, port: str) -> tuple[np.ndarray,
                                                                         np.ndarray, float]:
    """(d_in, d_out, s_io): unit directions (3,) of the input force and the output
    displacement, and s_io = sign(d_in . d_out). The ports must be a force and a
    displacement port on one region, along one line (a welded mass needs that)."""
    pin, pout = mf.ports.get(inp), mf.ports.get(port)
    if pin is None or pout is None or pin["direction"] is None or pout["direction"] is None:
        raise FileFormatError(f"file '{mf.path}': does not record the directions of ports "
                              f"'{inp}'/'{port}' (root attribute config_yaml), which scenario "
                              f"'{sc.name}' needs to couple a mass")
    if pin.get("kind") not in (None, "force") or pout.get("kind") not in (None, "displacement"):
        raise ConfigError(f"scenario '{sc.name}': a mass needs a force input and a "
                          f"displacement output; '{inp}' is a {pin.get('kind')} port and "
                          f"'{port}' a {pout.get('kind')} port", key=f"{sc.name}.input",
                          value=inp, expected="a force input port and a displacement output")
    d_in, d_out = pin["direction"], pout["direction"]
    s_io = float(d_in @ d_out)
    if abs(abs(s_io) - 1.0) > 1e-9:
        raise ConfigError(f"scenario '{sc.name}': input '{inp}' (direction {d_in.tolist()}) is "
                          f"not parallel to output '{port}' ({d_out.tolist()}); a welded mass "
                          "needs the force along the measured displacement",
                          key=f"{sc.name}.output", value=port,
                          expected=f"an output port parallel to input '{inp}'")
    if pin["region"] != pout["region"]:
        raise ConfigError(f"scenario '{sc.name}': input '{inp}' acts on region "
                          f"'{pin['region']}' but output '{port}' is on '{pout['region']}'; "
                          "the mass needs collocated ports", key=f"{sc.name}.output",
                          value=port, expected=f"an output port on region '{pin['region']}'")
    return d_in, d_out, math.copysign(1.0, s_io)


def mount_for(mf: ModelFile, sc: Scenario, key: str, port: str, d_out: np.ndarray,
              gravity: np.ndarray) -> tuple[Mount, float]:
    """The revolute mount (and the gravity moment per unit g along gravity) of a model."""
    if sc.joint is not None:
        P = np.asarray(sc.joint, float)
    else:
        pts = [mf.region_centroids[r] for r in mf.support_regions if r in mf.region_centroids]
        if not pts:
            raise FileFormatError(f"file '{mf.path}': no support region to put the joint on; "
                                  f"give scenario '{sc.name}'.joint [x, y, z]")
        P = np.mean(pts, axis=0)
    ez = np.array([0.0, 0.0, 1.0])
    if key == "lumped":
        lp = mf.lumped or {}
        need = ("element_mass", "element_com", "element_inertia", "element_extent",
                "joint_positions")
        if any(k not in lp for k in need):
            raise FileFormatError(f"file '{mf.path}': the lumped model lacks its element data")
        masses, coms, inertias = lp["element_mass"], lp["element_com"], lp["element_inertia"]
        tip = np.array([lp["element_extent"][-1, 1], *lp["joint_positions"][0, 1:]])
        rel = coms - P
        J = float(inertias[:, 2, 2].sum() + (masses * (rel[:, 0] ** 2 + rel[:, 1] ** 2)).sum())
        Mg = float(sum(np.cross(r, m * gravity)[2] for r, m in zip(rel, masses)))
    else:
        region = mf.ports.get(port, {}).get("region")
        if region not in mf.region_centroids:
            raise FileFormatError(f"file '{mf.path}': the region of port '{port}' is not stored")
        tip = mf.region_centroids[region]
        if not (math.isfinite(mf.body_mass) and np.all(np.isfinite(mf.body_inertia))):
            raise FileFormatError(f"file '{mf.path}': lacks body/mass, body/center_of_mass or "
                                  "body/inertia, which the spring mount needs")
        rel = mf.body_com - P
        J = float(mf.body_inertia[2, 2] + mf.body_mass * (rel[0] ** 2 + rel[1] ** 2))
        Mg = float(np.cross(rel, mf.body_mass * gravity)[2])
    arm = tip - P
    c_theta = float(np.cross(ez, arm) @ d_out)
    if abs(d_out[2]) > 1e-9 or abs(abs(c_theta) - np.linalg.norm(arm[:2])) > 1e-6 * max(
            np.linalg.norm(arm[:2]), 1e-12):
        raise ConfigError(f"scenario '{sc.name}': the spring mount rotates about z, so port "
                          f"'{port}' must measure along the circle about the joint (direction "
                          f"perpendicular to the arm {arm.round(6).tolist()} m in the x-y "
                          f"plane); it measures along {d_out.tolist()}",
                          key=f"{sc.name}.output", value=port,
                          expected="a port measuring along the circle about the joint")
    return Mount(sc.stiffness, sc.joint_damping, J, c_theta, arm, P), Mg


