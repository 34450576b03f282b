"""Pictures (issue 9): ``python -m pipeline plot FILE.h5`` writes a PNG per mode, an overview,
a frequency table (PNG + CSV), and for a reduced model its Bode magnitude and step
response; each PNG is checked to be written and non-trivial (size, not blank).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import FileFormatError
from pipeline.store.read import load_model
from pipeline.apps.plots import add_plot_parser, boundary_surface, is_slender, plot_file
from pipeline.store.read import read_stored_mesh
from pipeline.run import run_pipeline

ROOT = Path(__file__).resolve().parents[1]


def assert_picture(path: Path, min_bytes: int = 15_000) -> None:
    """A PNG that exists, is not tiny, and is not blank (pixel variance, colour present)."""
    from matplotlib.image import imread

    assert path.exists(), path
    assert path.stat().st_size >= min_bytes, (path, path.stat().st_size)
    img = imread(path)[..., :3]
    assert img.shape[0] >= 300 and img.shape[1] >= 400
    assert img.std() > 0.05, (path, img.std())              # not one flat colour
    non_white = np.mean(img.min(axis=2) < 0.9)
    assert non_white > 0.03, (path, non_white)              # something is drawn
    saturation = img.max(axis=2) - img.min(axis=2)
    assert np.mean(saturation > 0.2) > 0.005, path          # and some of it in colour


@pytest.fixture(scope="module")
def bracket_h5(tmp_path_factory) -> Path:
    """The bracket (a 3D picture), coarse, 3 modes, with its reduced model."""
    tmp = tmp_path_factory.mktemp("plots_bracket")
    cfg = load_config(ROOT / "configs" / "bracket.yaml", ["mesh.size=0.007", "modes.count=4"])
    return run_pipeline(cfg, tmp / "bracket.h5", mesh_dir=tmp).output


@pytest.fixture(scope="module")
def beam_h5(tmp_path_factory) -> Path:
    """The cantilever box (slender: a side view), modes only."""
    tmp = tmp_path_factory.mktemp("plots_beam")
    cfg = load_config(ROOT / "configs" / "cantilever.yaml",
                      ["mesh.size=0.025", "modes.count=3", "reduction=null", "lumped=null",
                       "filter=null", "ports=null"])
    return run_pipeline(cfg, tmp / "cantilever.h5", mesh_dir=tmp).output


def test_every_picture_of_a_reduced_model_is_written_and_non_trivial(bracket_h5, tmp_path):
    files = plot_file(bracket_h5, tmp_path / "pics")
    names = sorted(p.name for p in files if not p.name.startswith("static_von_mises_"))
    assert sum(p.name.startswith("static_von_mises_") for p in files) == \
        len(load_model(bracket_h5).input_names)  # one per input (tests/test_stress.py)
    assert names == sorted(["mode_01.png", "mode_02.png", "mode_03.png", "mode_04.png",
                            "modes.png", "frequencies.png", "frequencies.csv", "bode.png",
                            "step.png"])
    for p in files:
        if p.suffix == ".png":
            assert_picture(p)
    rows = list(csv.DictReader(open(tmp_path / "pics" / "frequencies.csv")))
    data = read_stored_mesh(bracket_h5)
    assert [float(r["frequency_hz"]) for r in rows] == pytest.approx(list(data.frequencies_hz))
    assert [r["in_reduced_model"] for r in rows] == ["1", "1", "1", "1"]
    assert not is_slender(data.points)


def test_slender_body_is_drawn_as_a_side_view_and_modes_only_file_has_no_bode(beam_h5, tmp_path):
    data = read_stored_mesh(beam_h5)
    assert is_slender(data.points)
    files = plot_file(beam_h5, tmp_path, modes=2)
    assert sorted(p.name for p in files) == ["frequencies.csv", "frequencies.png",
                                             "mode_01.png", "mode_02.png", "modes.png"]
    for p in files:
        if p.suffix == ".png":
            assert_picture(p)


def test_plot_command(beam_h5, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_plot_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["plot", str(beam_h5), "-o", str(tmp_path / "cli"), "--modes", "1"])
    assert args.func(args) == 0
    printed = capsys.readouterr().out.split()
    assert str(tmp_path / "cli" / "mode_01.png") in printed
    assert_picture(tmp_path / "cli" / "mode_01.png")
    # default folder: <stem>_plots next to the file
    args = parser.parse_args(["plot", str(beam_h5), "--modes", "1"])
    args.func(args)
    assert (beam_h5.parent / "cantilever_plots" / "frequencies.png").exists()


def test_plot_refuses_a_file_that_is_not_ours(tmp_path):
    bogus = tmp_path / "other.h5"
    import h5py

    with h5py.File(bogus, "w") as h5:
        h5["x"] = 1
    with pytest.raises(FileFormatError, match="schema"):
        plot_file(bogus, tmp_path)


def test_boundary_surface_of_a_tetrahedron_and_of_a_meshed_box(tmp_path):
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    s = boundary_surface(pts, np.array([[0, 1, 2, 3]]))
    assert s.triangles.shape == (4, 3) and s.feature_edges.shape == (6, 2)
    a, b, c = (pts[s.triangles[:, i]] for i in range(3))
    outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3 - pts.mean(0))
    assert (outward > 0).all()

    from pipeline.config import Geometry, MeshSpec
    from pipeline.fe.space import build_space
    from pipeline.fe.mesh import generate_mesh, read_mesh

    path = generate_mesh(Geometry("box", 0.3, 0.1, 0.05), MeshSpec(order=2, size=0.05,
                                                                    algorithm="delaunay"),
                         tmp_path / "box.msh")
    space = build_space(read_mesh(path), 2)
    s = boundary_surface(space.node_points, space.element_nodes)
    v = space.node_points
    a, b, c = (v[s.triangles[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    assert area == pytest.approx(2 * (0.3 * 0.1 + 0.3 * 0.05 + 0.1 * 0.05), rel=1e-9)
    # divergence theorem: outward orientation gives the volume
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert vol == pytest.approx(0.3 * 0.1 * 0.05, rel=1e-9)
    assert s.drawn.shape[0] == 4 * s.triangles.shape[0]       # quadratic: subdivided
    assert s.feature_edges.shape[1] == 3                      # through the edge midpoint
    ends = v[s.feature_edges[:, [0, 2]]]
    # the outline is the box's 12 edges: every point on two of its faces
    on_faces = [np.isclose(ends[..., k], 0) | np.isclose(ends[..., k], hi)
                for k, hi in enumerate((0.3, 0.1, 0.05))]
    assert (np.sum(on_faces, axis=0) >= 2).all()


# --------------------------------------------------------------------------- issue 21
import re  # noqa: E402

from pipeline.apps import plots as plots_module  # noqa: E402
from pipeline.apps import response_plots, views  # noqa: E402

#: the package's one way of writing a unit on an axis: "quantity [unit]"
UNIT_LABEL = re.compile(r"^.+ \[[^\[\]]+\]$")


def _captured_figures(monkeypatch):
    figs = []

    def keep(fig, out):
        figs.append(fig)
        return Path(out)

    monkeypatch.setattr(response_plots, "save_figure", keep)
    monkeypatch.setattr(plots_module, "save_figure", keep)
    return figs


def _axis_labels(fig):
    labels = []
    for ax in fig.axes:
        labels += [t for t in (ax.get_xlabel(), ax.get_ylabel()) if t]
    return labels


def test_every_axis_carries_its_unit_in_brackets(bracket_h5, beam_h5, monkeypatch, tmp_path):
    figs = _captured_figures(monkeypatch)
    response_plots.plot_bode(bracket_h5, tmp_path / "bode.png")
    response_plots.plot_step(bracket_h5, tmp_path / "step.png")
    data = read_stored_mesh(beam_h5)
    plots_module.plot_mode(data, 0, tmp_path / "m.png")
    plots_module.plot_frequency_table(data, tmp_path / "f.png")
    labels = [label for fig in figs for label in _axis_labels(fig)]
    # mode number (a count) is the one axis without a unit
    with_units = [label for label in labels if label != "mode"]
    assert with_units and all(UNIT_LABEL.match(label) for label in with_units), labels
    assert "f [Hz]" in labels and "phase [deg]" in labels and "|G| [m/N]" in labels
    # every mode picture has its colour bar
    assert any(ax.get_ylabel() == "|u| / max |u| [1]" for ax in figs[2].axes)


def test_bode_shows_magnitude_and_phase_of_a_known_system(bracket_h5, monkeypatch, tmp_path):
    import control

    from pipeline.store.read import load_model

    model = load_model(bracket_h5)
    f = np.array([50.0, 2000.0, 9000.0])
    G = response_plots.frequency_response(model.ss, f)
    ref = model.ss.frequency_response(2 * np.pi * f)
    np.testing.assert_allclose(np.abs(G), ref.magnitude, rtol=1e-9)
    # one mode, m x'' + c x' + k x = F: phase 0 below resonance, -90 deg at it, -180 above
    wn, z = 2 * np.pi * 100.0, 0.02
    one = control.ss([[0, 1], [-wn ** 2, -2 * z * wn]], [[0], [1]], [[1, 0]], [[0]])
    ph = response_plots.phase_deg(response_plots.frequency_response(
        one, np.array([1.0, 100.0, 1e4])))[0, 0]
    np.testing.assert_allclose(ph, [0.0, -90.0, -180.0], atol=0.5)
    figs = _captured_figures(monkeypatch)
    response_plots.plot_bode(bracket_h5, tmp_path / "bode.png")
    n_out = sum(name.endswith("/position") for name in model.output_names) or 1
    assert len(figs[0].axes) == 2 * n_out * len(model.input_names)  # magnitude and phase


def test_viewpoint_looks_across_the_motion():
    g = np.stack(np.meshgrid(*[np.linspace(-1, 1, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    twist_z = np.cross([0.0, 0.0, 1.0], g)
    elev, _ = views.view_for_mode(twist_z)
    assert elev > 45  # a rotation about z is seen from above (along its axis)
    heave_z = np.tile([0.0, 0.0, 1.0], (len(g), 1))
    elev, _ = views.view_for_mode(heave_z)
    assert abs(elev) < 30  # a motion along z is seen from the side


def test_a_twist_of_a_slender_body_is_drawn_end_on():
    x = np.stack(np.meshgrid(np.linspace(0, 0.5, 21), np.linspace(0, 0.02, 3),
                             np.linspace(0, 0.05, 4), indexing="ij"), -1).reshape(-1, 3)
    c = x.mean(axis=0)
    twist = np.cross([1.0, 0.0, 0.0], x - c) * x[:, :1]
    bend = np.zeros_like(x)
    bend[:, 1] = x[:, 0] ** 2
    assert views.is_twist(x, twist) and not views.is_twist(x, bend)
    assert views.is_twist(x, bend, "torsion_1")  # the file's label decides


def test_animation_is_a_looping_gif_of_the_moving_shape(beam_h5, tmp_path):
    from PIL import Image

    from pipeline.apps.animate import animate_mode

    data = read_stored_mesh(beam_h5)
    written = animate_mode(data, 0, tmp_path / "mode_01.gif", frames=8, mp4=False)
    assert written == [tmp_path / "mode_01.gif"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mode_01.gif"]  # no temporaries
    im = Image.open(written[0])
    assert im.n_frames == 8
    frames = []
    for k in (0, 2):  # amplitude 0 and 1: the shape has moved
        im.seek(k)
        frames.append(np.asarray(im.convert("RGB"), dtype=float))
    assert np.abs(frames[0] - frames[1]).mean() > 1.0


def test_batch_report_axes_carry_units(bracket_h5):
    from pipeline.apps.batch.gains import case_models, ratio_unit
    from pipeline.apps.batch.plots import key_label

    assert key_label("geometry.height") == "geometry.height [m]"
    assert key_label("material.E") == "material.E [Pa]"
    assert key_label("filter.cutoff_hz") == "filter.cutoff_hz [Hz]"
    ss = case_models(bracket_h5)
    pos = [n for n in ss.output_names if n.endswith("/position")]
    assert ratio_unit(ss, ss.input_names[0], pos[0]) == "m/N"
