"""Export to Exudyn and the round trip through Exudyn itself.

The format tests need only h5py. The integration test needs Exudyn (PyPI ``exudyn``,
the ``test`` extra): it is skipped, with the reason, only where ``import exudyn`` fails.

Tolerances:
- Exudyn's static tip deflection against the full-FE compliance stored in the file
  (T K^-1 F, a full solve): the export appends the static mode K^-1 F of the input port
  to the 10 clamped modes (issue 20), so the deflection is in the basis and Exudyn's
  linear static solve (Newton, relative tolerance 1e-10) reproduces it to the solver's
  tolerance and the round-off of K^-1 F, computed twice (the file's solve and the
  export's on the re-assembled K): 1e-10 + 2 c eps cond(K) (conftest.cond_eps). Was a
  fixed 1e-6, below 2 c eps cond(K) of the default mesh.
  Without the static mode it was 0.07% stiffer (the truncated modes' flexibility).
- Frequencies: the same eigenvalues of the same projected (K, M); the static mode is
  M- and K-orthogonal to the modes, so the first 10 Ritz values are unchanged up to the
  eigensolver's error: half of conftest.eigenvalue_rtol of the clamped pencil (was 1e-6).
- cond(K) and lambda_max / lambda_1 grow as h^-2 (lambda_max of a second-order elliptic
  operator ~ h^-2, the lowest eigenvalues converge): they are computed on the clamped
  0.02 m mesh of the same box and scaled by (0.02 / h)^2 (_round_off_at).
- Exudyn's inertia invariants against ours: both are the same finite sums over the same
  M and basis, so round-off, 1e-10 relative to the largest entry of each term.
- Geometry of the exported boundary: exact sums, 1e-12.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import build_model, cond_eps, eigenvalue_rtol, record_tolerance
from pipeline.errors import ConfigError, FileFormatError
from pipeline.apps.exports import EXPORTERS, default_output, export
from pipeline.store.read import read_csr
from pipeline.apps.exports.exudyn import boundary_faces, export_exudyn, region_node_weights
from pipeline.store.schema import craig_bampton_datasets, csr_datasets, exudyn_datasets
from pipeline.store.tree import Dataset
from pipeline.solve.eigen import solve_modes
from pipeline.store.h5file import content_digest, write_file

try:  # the integration test needs Exudyn itself
    import exudyn  # noqa: F401

    EXUDYN_ERROR = None
except Exception as exc:  # ImportError, or a binary wheel that fails to load
    EXUDYN_ERROR = f"exudyn cannot be imported here ({type(exc).__name__}: {exc}); " \
                   "install the test extra: pip install exudyn"

L, H, W = 0.5, 0.02, 0.05


def _append(path: Path, tree: dict[str, Dataset]) -> None:
    """Add datasets to one of our files and refresh its checksum (what the run will do
    when it includes exudyn_datasets)."""
    with h5py.File(path, "a") as h5:
        for key, ds in tree.items():
            dset = h5.create_dataset(key, data=ds.as_array())
            dset.attrs["units"] = ds.units
            for k, v in ds.attrs.items():
                dset.attrs[k] = v
        h5.attrs["content_sha256"] = content_digest(h5)


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    """A small clamped beam written in our layout (core datasets + exudyn_datasets)."""
    tmp = tmp_path_factory.mktemp("exu")
    m = build_model(tmp, 0.2, H, W, size=0.02)
    modes = solve_modes(m.K, m.M, 4, backend="superlu")
    shapes = np.zeros((m.space.n_dofs, 4))
    shapes[m.free] = modes.shapes
    fixed = np.setdiff1d(np.arange(m.space.n_dofs), m.free)
    tree = {
        "mesh/points": Dataset(m.space.node_points, "m"),
        "mesh/cells/tetra10": Dataset(m.space.element_nodes.astype(np.int64), "1"),
        "mesh/fixed_dofs": Dataset(fixed, "1"),
        "modes/shapes": Dataset(shapes.reshape(m.space.n_nodes, 3, 4), "kg^-1/2"),
        "modes/omega2": Dataset(modes.omega2, "rad^2/s^2"),
        **{f"mesh/regions/{k}": Dataset(v.astype(np.int64), "1") for k, v in m.regions.items()},
    }
    bare = write_file(tmp / "bare.h5", tree, {"modes": {"n_rigid": 0}}, {"name": "small"})
    tree.update(exudyn_datasets(m.K_full, m.M_full))
    full = write_file(tmp / "small.h5", tree, {"modes": {"n_rigid": 0}}, {"name": "small"})
    return m, modes, bare, full


def test_export_writes_the_tagged_layout_exudyn_loads(small_file, tmp_path):
    m, modes, _, path = small_file
    out = export(path, "exudyn", tmp_path / "small.hdf5")
    untagged = []
    with h5py.File(out, "r") as h5:
        h5.visititems(lambda name, obj: untagged.append(name)
                      if "datatype" not in obj.attrs else None)
        assert not untagged, untagged
        assert set(h5) >= {"nodes", "elements", "massMatrix", "stiffnessMatrix", "surface",
                           "nodeSets", "modeBasis", "eigenValues", "metaData"}
        assert h5["massMatrix"].attrs["datatype"] == "csr_matrix"
        # no port loads given (the Python API, no fe_data): the file says its statics
        # are the truncated ones
        assert h5["metaData/statics"][()].decode().startswith("truncated")
        assert h5["elements/item_0/Tet10"].shape == m.space.element_nodes.shape
        np.testing.assert_array_equal(h5["nodes/Position"][()], m.space.node_points)
        basis = h5["modeBasis/matrix"][()]
        assert h5["modeBasis/type"][()].decode() == "NormalModes"
        names = [h5[f"nodeSets/item_{i}/Name"][()].decode() for i in range(len(h5["nodeSets"]))]
        assert {"root", "tip"} <= set(names)
        M = h5["massMatrix"]
        from scipy.sparse import csr_matrix

        Mx = csr_matrix((M["data"][()], M["indices"][()], M["indptr"][()]),
                        shape=tuple(M["shape"][()]))
    # symmetric storage mirrors the upper triangle: equal up to the assembly's round-off
    # asymmetry (~1e-16 relative)
    assert abs(Mx - m.M_full).max() <= 1e-12 * abs(m.M_full).max()
    assert basis.shape == (m.space.n_dofs, 4)
    np.testing.assert_allclose(basis[m.free], modes.shapes)


def test_export_refusals_and_registry(small_file, tmp_path):
    _, _, bare, full = small_file
    with pytest.raises(FileFormatError, match="must end in '.hdf5'"):
        export_exudyn(full, tmp_path / "x.h5")
    # the Python API without fe_data: the error names the config key and the command
    # that re-assembles (it named a Python function before issue 20)
    with pytest.raises(FileFormatError, match="has no /fe.*'connections'.*export FILE --to "
                       "exudyn.*re-assembles") as err:
        export_exudyn(bare, tmp_path / "x.hdf5")
    assert err.value.key == "connections"
    with pytest.raises(ConfigError, match="expected one of exudyn"):
        export(full, "nope")
    assert "exudyn" in EXPORTERS
    assert default_output(Path("out/cantilever.h5"), "exudyn") == Path(
        "out/cantilever.exudyn.hdf5")


def test_sparse_storage_round_trip(small_file, tmp_path):
    m = small_file[0]
    path = write_file(tmp_path / "k.h5", csr_datasets(m.K_full, "fe/K", "N/m", "K"))
    with h5py.File(path, "r") as h5:
        assert h5["fe/K/data"].attrs["storage"] == "upper"
        assert h5["fe/K/data"].size < 0.6 * m.K_full.nnz
        assert abs(read_csr(h5, "fe/K") - m.K_full).max() <= 1e-12 * abs(m.K_full).max()


def test_boundary_faces_and_region_weights(small_file):
    m = small_file[0]
    x = m.space.node_points
    trigs, trigs6 = boundary_faces(x, m.space.element_nodes.astype(np.int64))
    a, b, c = (x[trigs[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(n, axis=1).sum()
    np.testing.assert_allclose(area, 2 * (0.2 * H + 0.2 * W + H * W), rtol=1e-12)
    centre = np.array([0.1, H / 2, W / 2])
    assert np.all(np.einsum("ij,ij->i", n, (a + b + c) / 3 - centre) > 0)  # outward
    np.testing.assert_allclose(x[trigs6[:, 3]], 0.5 * (a + b), atol=1e-15)
    np.testing.assert_allclose(x[trigs6[:, 5]], 0.5 * (c + a), atol=1e-15)
    nodes, w = region_node_weights(x, m.space.element_nodes.astype(np.int64), m.regions["tip"])
    assert abs(w.sum() - 1) < 1e-12
    np.testing.assert_allclose(w @ x[nodes], [0.2, H / 2, W / 2], atol=1e-12)
    assert np.all(np.abs(x[nodes, 0] - 0.2) < 1e-12)


# --------------------------------------------------------------------------- round trip
@pytest.fixture(scope="module")
def cantilever_file(tmp_path_factory):
    """configs/cantilever.yaml at mesh.size 0.01 through run_pipeline (no 'connections',
    so no /fe in the file: the export re-assembles M and K), and K, M assembled here for
    the invariant comparison."""
    from pipeline.fe.assemble import assemble_stiffness_mass
    from pipeline.config import load_config
    from pipeline.fe.space import build_space
    from pipeline.fe.mesh import read_mesh
    from pipeline.run import run_pipeline

    tmp = tmp_path_factory.mktemp("cantilever")
    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs/cantilever.yaml", ["mesh.size=0.01"])
    result = run_pipeline(cfg, tmp / "cantilever.h5", mesh_dir=tmp)
    with h5py.File(result.output, "r") as h5:
        source = h5["mesh"].attrs["source"]
        points = h5["mesh/points"][()]
    space = build_space(read_mesh(source), cfg.mesh.order)
    np.testing.assert_array_equal(space.node_points, points)
    K, M = assemble_stiffness_mass(space, cfg.material)
    return result.output, K, M


def clamped_tip_in_exudyn(out: Path):
    """Load the exported file in Exudyn, clamp the root node set, push the tip node set
    with 1 N along -y; (static tip deflection along y, frequencies Hz, fem, cms)."""
    import exudyn as exu
    from exudyn.FEM import FEMinterface, ObjectFFRFreducedOrderInterface
    from exudyn.itemInterface import (GenericJoint, LoadForceVector, MarkerBodyRigid,
                                      MarkerSuperElementPosition, MarkerSuperElementRigid,
                                      ObjectGround, SensorMarker, VGenericJoint)

    fem = FEMinterface()
    fem.LoadFromFile(str(out))
    cms = ObjectFFRFreducedOrderInterface(fem)
    SC = exu.SystemContainer()
    mbs = SC.AddSystem()
    body = cms.AddObjectFFRFreducedOrder(mbs, positionRef=[0, 0, 0])["oFFRFreducedOrder"]
    sets = {ns["Name"]: ns for ns in fem.nodeSets}
    root, tip = sets["root"], sets["tip"]
    ground = mbs.AddObject(ObjectGround(referencePosition=[0, 0, 0]))
    # the rigid marker sits at the weighted centroid of the root nodes: put the ground there
    xyz = fem.GetNodePositionsAsArray()
    centre = list(np.asarray(root["NodeWeights"]) @ xyz[root["NodeNumbers"]])
    m_ground = mbs.AddMarker(MarkerBodyRigid(bodyNumber=ground, localPosition=centre))
    m_root = mbs.AddMarker(MarkerSuperElementRigid(
        bodyNumber=body, meshNodeNumbers=np.array(root["NodeNumbers"]),
        weightingFactors=root["NodeWeights"], offset=[0, 0, 0]))
    mbs.AddObject(GenericJoint(markerNumbers=[m_ground, m_root], constrainedAxes=[1] * 6,
                               visualization=VGenericJoint(show=False)))  # clamp the root
    m_tip = mbs.AddMarker(MarkerSuperElementPosition(
        bodyNumber=body, meshNodeNumbers=np.array(tip["NodeNumbers"]),
        weightingFactors=tip["NodeWeights"]))
    mbs.AddLoad(LoadForceVector(markerNumber=m_tip, loadVector=[0, -1.0, 0]))  # 1 N along -y
    sensor = mbs.AddSensor(SensorMarker(markerNumber=m_tip, storeInternal=True,
                                        outputVariableType=exu.OutputVariableType.Position))
    mbs.Assemble()
    settings = exu.SimulationSettings()
    settings.staticSolver.newton.relativeTolerance = 1e-10
    settings.staticSolver.verboseMode = 0
    settings.solution.file.write = False  # no solution/ folder in the cwd
    p0 = np.array(mbs.GetSensorValues(sensor))
    mbs.SolveStatic(settings)
    deflection = (np.array(mbs.GetSensorValues(sensor)) - p0)[1]
    omega2, _ = mbs.ComputeODE2Eigenvalues(settings)
    f_exudyn = np.sqrt(np.sort(np.abs(omega2))) / (2 * np.pi)

    return deflection, f_exudyn, fem, cms


def _round_off_at(tmp_path, size):
    """(static, frequency) relative bounds for the clamped cantilever box at mesh size
    ``size``: 1e-10 (Exudyn's Newton tolerance) + 2 c eps cond(K), and half of
    eigenvalue_rtol, from the 0.02 m mesh scaled by (0.02 / size)^2 (module docstring)."""
    coarse = build_model(tmp_path, 0.5, 0.02, 0.05, size=0.02)
    scale = max(1.0, (0.02 / size) ** 2)
    return (1e-10 + 2 * scale * cond_eps(coarse.K),
            0.5 * scale * eigenvalue_rtol(coarse.K, coarse.M))


def _check_against_full_fe(tmp_path, size, deflection, full_fe, f_exudyn, f_ours, name):
    static_bound, frequency_bound = _round_off_at(tmp_path, size)
    static = abs(deflection / full_fe - 1)
    record_tolerance(f"test_exudyn::{name}_static", static, static_bound)
    assert static < static_bound, (deflection, full_fe, static_bound)
    frequency = float(np.max(np.abs(f_exudyn[:10] / f_ours[:10] - 1)))
    record_tolerance(f"test_exudyn::{name}_frequencies", frequency, frequency_bound)
    assert frequency < frequency_bound, (f_exudyn[:10], f_ours[:10], frequency_bound)
    return static_bound


@pytest.mark.skipif(EXUDYN_ERROR is not None, reason=EXUDYN_ERROR or "")
def test_exudyn_round_trip(cantilever_file, tmp_path):
    from pipeline.reduce.ffrf import ffrf_invariants
    from pipeline.store.h5file import read_strings

    from pipeline.cli.export import run_export

    h5_path, K, M = cantilever_file
    with h5py.File(h5_path, "r") as h5:
        assert "fe" not in h5   # what made the export fail before issue 20
    out = run_export(h5_path, "exudyn", tmp_path / "cantilever.hdf5")
    with h5py.File(out, "r") as h5:
        assert h5["metaData/statics"][()].decode().startswith("exact")
        assert "re-assembled" in h5["metaData/matrices"][()].decode()
    deflection, f_exudyn, fem, cms = clamped_tip_in_exudyn(out)
    with h5py.File(h5_path, "r") as h5:
        ins = read_strings(h5["statespace/input_names"])
        outs = read_strings(h5["statespace/output_names"])
        A, B, C, D = (h5[f"statespace/{k}"][()] for k in "ABCD")
        f_ours = h5["modes/frequencies_hz"][()]
        points = h5["mesh/points"][()]
        full_fe = float(np.ravel(h5["statespace/static_compliance"][()])[0])
    # our reduced model: DC gain of tip_force_y (1 N along -y) -> tip_y position
    row, col = outs.index("tip_y/position"), ins.index("tip_force_y")
    dc = (D - C @ np.linalg.solve(A, B))[row, col]
    print(f"exudyn static deflection {deflection:.12e} m, full FE {full_fe:.12e} m")
    static_bound = _check_against_full_fe(tmp_path, 0.01, deflection, full_fe, f_exudyn,
                                          f_ours, "round_trip")
    # and so does our own corrected state space (the same K^-1 F, a small dense solve)
    assert abs(dc / full_fe - 1) < static_bound

    # Exudyn's own inertia invariants against ours (pipeline.reduce.ffrf), same basis
    Psi = fem.modeBasis["matrix"]
    inv = ffrf_invariants(M, points, Psi, K)
    n = Psi.shape[1]
    Xk = cms.mXRefTildePsiTilde.reshape(3, n, 3).transpose(1, 0, 2)
    pairs = {
        "mass": (inv.mass, cms.totalMass),
        "center_of_mass": (inv.center_of_mass, cms.chiU),
        "inertia": (inv.inertia, cms.inertiaLocal),
        "translational_coupling": (inv.translational_coupling, cms.mPhitTPsi),
        "rotational_coupling": (inv.rotational_coupling, -cms.mXRefTildePsi),
        "modal_mass": (inv.modal_mass, cms.massMatrixReduced),
        "modal_stiffness": (inv.modal_stiffness, cms.stiffnessMatrixReduced),
        "inertia_first_order": (inv.inertia_first_order, Xk + Xk.transpose(0, 2, 1)),
        "inertia_second_order": (inv.inertia_second_order,
                                 cms.mPsiTildePsiTilde.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)),
        "gyroscopic_coupling": (inv.gyroscopic_coupling,
                                -cms.mPsiTildePsi.reshape(n, 3, n).transpose(0, 2, 1)),
    }
    for name, (ours, theirs) in pairs.items():
        ours, theirs = np.asarray(ours, float), np.asarray(theirs, float)
        scale = max(np.abs(theirs).max(), 1e-300)
        # Exudyn rounds reduced-matrix entries below 1e-13 of the largest to zero
        assert np.abs(ours - theirs).max() <= 1e-10 * scale, name


def test_craig_bampton_basis_is_exported_without_the_reference_interface(small_file, tmp_path):
    """With /craig_bampton in the file, the export carries the CB basis less the six static
    modes of the first interface (the frame follows it), as Exudyn's own HCB modes do."""
    from types import SimpleNamespace

    from pipeline.reduce.interfaces import make_interfaces
    from pipeline.reduce.craig_bampton import craig_bampton

    m, _, _, path = small_file
    ifs = make_interfaces(m.space, m.regions, [
        SimpleNamespace(name="root", region="root", point=[0, H / 2, W / 2], coupling="rigid"),
        SimpleNamespace(name="tip", region="tip", point=[0.2, H / 2, W / 2],
                        coupling="distributing")])
    cb = craig_bampton(m.space, m.K_full, m.M_full, ifs, 3, backend="superlu")
    cb_file = tmp_path / "cb.h5"
    with h5py.File(path, "r") as src, h5py.File(cb_file, "w") as dst:
        for key in src.attrs:
            dst.attrs[key] = src.attrs[key]
        for key in src:
            src.copy(src[key], dst, name=key)
    _append(cb_file, craig_bampton_datasets(cb))
    out = export(cb_file, "exudyn", tmp_path / "cb.hdf5")
    with h5py.File(out, "r") as h5:
        assert h5["modeBasis/type"][()].decode() == "HCBmodes"
        basis = h5["modeBasis/matrix"][()]
        assert "tip.x" in h5["metaData/basis"][()].decode()
        eig = h5["eigenValues"][()]
    np.testing.assert_allclose(basis, cb.shapes[:, 6:], atol=1e-12 * np.abs(cb.shapes).max())
    np.testing.assert_allclose(np.sqrt(eig) / (2 * np.pi), cb.frequencies_hz(["root"]),
                               rtol=1e-8)


@pytest.mark.slow
@pytest.mark.skipif(EXUDYN_ERROR is not None, reason=EXUDYN_ERROR or "")
def test_exudyn_from_the_default_cantilever_config(tmp_path):
    """configs/cantilever.yaml as shipped (mesh.size 0.005): the command-line export,
    loaded in Exudyn, gives the full-FE static tip deflection and our 10 frequencies
    (tolerances as in the module docstring)."""
    from pipeline.cli.export import run_export
    from pipeline.config import load_config
    from pipeline.run import run_pipeline

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs/cantilever.yaml")
    h5_path = run_pipeline(cfg, tmp_path / "cantilever.h5", mesh_dir=tmp_path).output
    out = run_export(h5_path, "exudyn")
    deflection, f_exudyn, _, _ = clamped_tip_in_exudyn(out)
    with h5py.File(h5_path, "r") as h5:
        full_fe = float(np.ravel(h5["statespace/static_compliance"][()])[0])
        f_ours = h5["modes/frequencies_hz"][()]
    print(f"default mesh: exudyn {deflection:.12e} m, full FE {full_fe:.12e} m, "
          f"f1 {f_exudyn[0]:.6f} / {f_ours[0]:.6f} Hz")
    _check_against_full_fe(tmp_path, cfg.mesh.size, deflection, full_fe, f_exudyn, f_ours,
                           "default_config")
