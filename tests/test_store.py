"""HDF5 output: what we computed is what a plain h5py reader and `inspect` see; writes
are atomic; the loader gives back the model bit for bit; foreign files are refused."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from conftest import ROOT
from pipeline import load_model
from pipeline.config import load_config
from pipeline.errors import FileFormatError
from pipeline.store.tree import Dataset
from pipeline.run import run_pipeline
from pipeline.store.h5file import SCHEMA, SCHEMA_VERSION, open_verified, write_file
from pipeline.apps.summary import summarize


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("store")
    cfg = load_config(ROOT / "configs/cantilever.yaml", ["mesh.size=0.02"])
    return run_pipeline(cfg, tmp / "c.h5", mesh_dir=tmp)


def test_file_holds_what_was_computed(result):
    with h5py.File(result.output, "r") as h5:
        assert h5.attrs["schema"] == SCHEMA
        assert int(h5.attrs["schema_version"]) == SCHEMA_VERSION
        for key in ("pipeline_version", "created_utc", "config_yaml", "content_sha256"):
            assert key in h5.attrs
        np.testing.assert_array_equal(h5["modes/frequencies_hz"][()], result.frequencies_hz)
        assert list(h5["modes/labels"].asstr()[()]) == result.labels
        assert float(h5["body/mass"][()]) == result.mass
        n_p = h5["mesh/points"].shape[0]
        assert h5["modes/shapes"].shape == (n_p, 3, len(result.frequencies_hz))
        assert h5["mesh/cells/tetra10"].shape[1] == 10
        missing = []
        h5.visititems(lambda n, o: missing.append(n) if isinstance(o, h5py.Dataset)
                      and "units" not in o.attrs else None)
        assert missing == [], f"datasets without units: {missing}"
        assert "cantilever" in h5.attrs["config_yaml"]


def test_mode_shapes_are_m_orthonormal_in_the_file(result):
    """The stored shapes (per mesh point) are M-orthonormal with the FE mass matrix."""
    from pipeline.fe.assemble import assemble_stiffness_mass
    from pipeline.fe.space import build_space
    from pipeline.fe.mesh import read_mesh

    with h5py.File(result.output, "r") as h5:
        shapes = h5["modes/shapes"][()]
        source = h5["mesh"].attrs["source"]
        points = h5["mesh/points"][()]
    space = build_space(read_mesh(source), 2)
    np.testing.assert_array_equal(space.node_points, points)
    _, M = assemble_stiffness_mass(space, result.config.material)
    Phi = shapes.reshape(-1, shapes.shape[2])
    np.testing.assert_allclose(Phi.T @ (M @ Phi), np.eye(Phi.shape[1]), atol=1e-8)


def test_inspect_shows_the_same_numbers(result):
    text = summarize(result.output)
    for f, label in zip(result.frequencies_hz, result.labels):
        assert f"{f:12.4f}  {label}" in text  # the table under "f [Hz]"
    assert "f [Hz]" in text
    assert "mass 1.35 kg" in text and "statespace_filtered" in text


def test_loader_gives_back_the_model_bit_for_bit(result):
    import control as ct

    reduced = result.extras["reduced"].statespace
    filtered = result.extras["filtered"]
    model = load_model(result.output)
    for k in "ABCD":
        np.testing.assert_array_equal(getattr(model.ss, k), getattr(reduced, k))
        np.testing.assert_array_equal(getattr(model.ss_filtered, k), getattr(filtered, k))
    assert model.input_names == ("tip_force_y",)
    assert model.output_names == ("tip_y/position", "tip_y/velocity", "tip_y/acceleration")
    # not two solves with K: the stored static compliance G enters D = G - (modal part)
    # itself, so G(0) = D + (modal part) is G up to the round-off of that sum and of the
    # small, modally diagonal A (measured 0 on AMD Zen 3); 1e-9 is ~4e6 eps of margin
    np.testing.assert_allclose(ct.dcgain(model.ss)[0], model.static_compliance[0, 0], rtol=1e-9)
    assert model.filter_kind == "third_order" and model.cutoff_hz == 5000.0


def test_loaded_model_holds_the_plant_once(result):
    """The README's attributes are views of one StateSpace: the raw matrices are the plant's
    own arrays and the python-control system is built from them on first use."""
    model = load_model(result.output)
    for k in "ABCD":
        assert model.matrices[k] is getattr(model.plant, k)
        assert model.matrices_filtered[k] is getattr(model.filtered, k)
    assert model.ss is model.ss  # built once
    assert model.frequencies_hz.size == len(model.labels) == result.frequencies_hz.size
    assert model.static_compliance.shape == (1, 1) and model.compliance_rows == ("tip_y",)
    assert model.damping_ratios.shape == model.retained_frequencies_hz.shape
    assert model.input_units == ("N",) and model.name == "cantilever"


def test_interrupted_write_leaves_nothing_under_the_final_name(tmp_path, monkeypatch):
    import pipeline.store.h5file as store

    target = tmp_path / "model.h5"
    tree = {f"g/d{i}": Dataset(np.arange(10.0) * i, "m") for i in range(5)}
    write_file(target, tree)
    before = target.read_bytes()
    calls = {"n": 0}
    real = store._write_dataset

    def crash_after_two(h5, path, ds):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt("simulated interruption")
        real(h5, path, ds)

    monkeypatch.setattr(store, "_write_dataset", crash_after_two)
    with pytest.raises(KeyboardInterrupt):
        write_file(target, {k: Dataset(v.data + 1, "m") for k, v in tree.items()})
    assert target.read_bytes() == before  # the old complete file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.h5"]  # no partial left
    with pytest.raises(KeyboardInterrupt):
        write_file(tmp_path / "new.h5", tree)
    assert not (tmp_path / "new.h5").exists()


def test_truncated_and_foreign_files_are_refused(result, tmp_path):
    data = result.output.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match="cut.h5"):
        load_model(cut)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as h5:
        h5["x"] = 1
    with pytest.raises(FileFormatError, match="schema attribute is None"):
        open_verified(foreign)
    newer = tmp_path / "newer.h5"
    newer.write_bytes(data)
    with h5py.File(newer, "r+") as h5:
        h5.attrs["schema_version"] = 99
    with pytest.raises(FileFormatError, match="schema_version 99 is not known.*version\\(s\\) 1"):
        load_model(newer)


def test_bit_flip_in_a_dataset_is_detected(result, tmp_path):
    flipped = tmp_path / "flipped.h5"
    flipped.write_bytes(result.output.read_bytes())
    with h5py.File(flipped, "r+") as h5:
        h5["modes/frequencies_hz"][0] += 1e-9
    with pytest.raises(FileFormatError, match="checksum mismatch"):
        load_model(flipped)


# --------------------------------------------------------------------------- every model
def test_load_model_gives_every_model_as_one_statespace_type(result):
    from pipeline.reduce.statespace import StateSpace

    model = load_model(result.output)
    assert set(model.models) == {"plant", "filtered", "lumped"}
    for name, ss in model.models.items():
        assert isinstance(ss, StateSpace) and ss.label == name
    # the plant is the python-control system bit for bit
    np.testing.assert_array_equal(model.plant.A, model.ss.A)
    np.testing.assert_array_equal(model.plant.D, model.ss.D)
    # residual correction: the reduced model's static gain is the full-FE T K^-1 F; the
    # position rows of G(0) are sums of O(|G|) terms, so round-off ~ n_states eps |G|
    G = model.static_compliance
    rows = [model.plant.output_names.index(f"{p}/position") for p in model.plant.ports]
    np.testing.assert_allclose(model.plant.dc_gain()[rows], G, rtol=0,
                               atol=1e3 * np.finfo(float).eps * np.abs(G).max())
    # the filter has unit DC gain: the filtered model's static positions are the plant's
    np.testing.assert_allclose(model.filtered.dc_gain()[rows], G, rtol=1e-9)
    # the lumped chain's static tip compliance, stored beside it, is its own G(0)
    with h5py.File(result.output, "r") as h5:
        stored = float(h5["lumped/tip_compliance"][()])
    lumped = model.lumped
    position = lumped.output_names.index("tip_position")
    assert np.isclose(abs(lumped.dc_gain()[position, 0]), stored, rtol=1e-9)
    with pytest.raises(FileFormatError) as exc:
        model.model("craig_bampton")
    assert exc.value.value == "craig_bampton" and exc.value.exit_code == 7


@pytest.fixture(scope="module")
def connection_file(tmp_path_factory):
    """A connection-only run: /fe, /connections and /craig_bampton, no /statespace."""
    tmp = tmp_path_factory.mktemp("conn")
    cfg = load_config(ROOT / "configs/cantilever_connection.yaml", ["mesh.size=0.02",
                                                                   "craig_bampton.modes=4"])
    return run_pipeline(cfg, tmp / "conn.h5", mesh_dir=tmp).output


def test_connection_only_file_loads_its_connection_and_craig_bampton_models(connection_file):
    out = connection_file
    model = load_model(out)
    assert model.plant is None and model.ss is None
    assert set(model.models) == {"connection/root", "craig_bampton"}
    conn = model.model("connection/root")
    # inputs: a_P (6), then the wrench at the child connection 'tip' (6)
    assert conn.n_inputs == 12 and conn.input_units[:6] == ("m/s^2",) * 3 + ("rad/s^2",) * 3
    assert conn.input_units[6:] == ("N",) * 3 + ("N m",) * 3
    with h5py.File(out, "r") as h5:  # the feedthrough's top-left block is the residual mass
        np.testing.assert_array_equal(conn.D[:6, :6], h5["connections/root/D_P0"][()])
    cb = model.craig_bampton
    n = 2 * 6 + 4  # two interfaces with six coordinates each, four fixed-interface modes
    assert cb.M.shape == (n, n) and len(cb.coordinate_names) == n
    np.testing.assert_allclose(cb.M, cb.M.T, rtol=0, atol=1e-12 * np.abs(cb.M).max())
    with pytest.raises(FileFormatError, match="no plant model"):
        load_model(out, require_plant=True)


def test_summary_reader_agrees_with_the_model_loader(result):
    """read_summary (inspect, JSON export, batch cache) reads what load_model reads."""
    from pipeline.store.summary import read_summary

    s = read_summary(result.output)
    lm = load_model(result.output)
    np.testing.assert_array_equal(s.modes.frequencies_hz, lm.frequencies_hz)
    assert s.modes.labels == lm.labels and s.body.mass == lm.mass
    assert list(s.models) == ["statespace", "statespace_filtered", "lumped"]
    for summary, model in ((s.plant, lm.plant), (s.filtered, lm.filtered),
                           (s.lumped, lm.lumped)):
        assert summary.n_states == model.A.shape[0]
        assert summary.input_names == model.input_names
        assert summary.output_names == model.output_names
    for k, m in zip("ABCD", s.plant.matrices):
        np.testing.assert_array_equal(m, getattr(lm.plant, k))
    assert s.filtered.filter_kind == lm.filtered.filter_kind
    assert s.mesh.n_dofs == 3 * s.mesh.n_points and s.run.times_s


def test_summary_of_a_modes_only_file(tmp_path):
    """A config without reduction, filter, lumped chain or ports: every reader of the
    summary takes the file (no models), as before the summary reader."""
    from pipeline.apps.exports.summary_json import summary
    from pipeline.store.summary import read_summary

    cfg = load_config(ROOT / "configs/cantilever.yaml",
                      ["mesh.size=0.025", "modes.count=3", "reduction=null", "filter=null",
                       "lumped=null", "ports=null"])
    path = run_pipeline(cfg, tmp_path / "m.h5", mesh_dir=tmp_path).output
    s = read_summary(path)
    assert s.models == {} and s.plant is None and s.modes.frequencies_hz.size == 3
    assert "models    none (modes only)" in summarize(path)
    data = summary(path)
    assert data["reduced_model"] is None and data["lumped_model"] is None
    assert [m["mode"] for m in data["modes"]] == [1, 2, 3]


def test_fe_model_reader_agrees_with_the_mesh_reader_and_read_csr(result, connection_file):
    """read_fe_model (the Exudyn export's reader) gives the mesh read_stored_mesh gives,
    /fe's M and K as read_csr reads them, and the basis asked for."""
    from pipeline.store.read import read_csr, read_fe_model, read_stored_mesh

    for path, has_fe in ((result.output, False), (connection_file, True)):
        mesh, body = read_stored_mesh(path), read_fe_model(path, "modes")
        assert body.has_fe == mesh.has_fe == has_fe
        assert (body.name, body.cell_type) == (mesh.name, mesh.cell_type)
        for got, ref in ((body.points, mesh.points), (body.cells, mesh.cells),
                         (body.fixed_dofs, mesh.fixed_dofs)):
            assert got.dtype == ref.dtype
            np.testing.assert_array_equal(got, ref)
        assert list(body.regions) == list(mesh.regions)
        for name, tris in mesh.regions.items():
            np.testing.assert_array_equal(body.regions[name], tris)
        assert body.basis.kind == "modes" and body.n_dofs == 3 * mesh.points.shape[0]
        np.testing.assert_array_equal(body.basis.shapes,
                                      mesh.shapes.reshape(body.n_dofs, -1))
        with h5py.File(path, "r") as h5:
            assert body.basis.n_rigid == int(h5["modes"].attrs.get("n_rigid", 0))
            if has_fe:
                for got, key in ((body.M, "fe/mass_matrix"), (body.K, "fe/stiffness_matrix")):
                    ref = read_csr(h5, key)
                    assert got.shape == ref.shape and (got != ref).nnz == 0
    assert body.M is not None and body.K is not None  # the connection file holds /fe

    # auto: the Craig-Bampton basis where the file has one, as load_model names it
    cb_body, cb = read_fe_model(connection_file), load_model(connection_file).craig_bampton
    assert cb_body.basis.kind == "craig_bampton" and cb_body.basis.n_rigid == 0
    assert cb_body.basis.names == cb.coordinate_names
    assert cb_body.basis.interface_names == cb.interface_names
    with h5py.File(connection_file, "r") as h5:
        np.testing.assert_array_equal(cb_body.basis.shapes,
                                      h5["craig_bampton/shapes"][()].reshape(cb_body.n_dofs, -1))
    assert read_fe_model(result.output).basis.kind == "modes"
    with pytest.raises(FileFormatError, match="no /craig_bampton/shapes"):
        read_fe_model(result.output, "craig_bampton")
    with pytest.raises(ValueError, match="not one of auto, modes, craig_bampton"):
        read_fe_model(result.output, "nope")
