import json
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam2d.cli.main import main
from slam2d.graph import FactorGraph, Values, chi2, optimize
from slam2d.graph.synthetic import manhattan_walk
from slam2d.io import (
    GraphFormatError,
    GraphFormatWarning,
    detect_format,
    read_g2o,
    read_isam,
    read_toro,
    write_g2o,
    write_isam,
    write_toro,
)


def _landmark_graph(rng):
    sg = manhattan_walk(rng, num_poses=40)
    g = sg.graph
    lm = rng.uniform(-5, 5, (4, 2))
    from slam2d.geometry import se2

    pi = np.arange(0, 40, 3)
    li = pi % 4
    g.add_point(pi, li, se2.inverse_transform_points(sg.truth.poses[pi], lm[li]), np.diag([100.0, 50.0]))
    vals = Values(sg.initial.pose_keys, sg.initial.poses, np.arange(4), lm + 0.1)
    return g, vals


def test_g2o_round_trip(tmp_path, rng):
    g, vals = _landmark_graph(rng)
    p = tmp_path / "a.g2o"
    write_g2o(p, g, vals)
    gf = read_g2o(p)
    assert gf.initial_guess == "vertices"
    np.testing.assert_array_equal(gf.values.poses, vals.poses)
    np.testing.assert_array_equal(gf.values.points, vals.points)
    assert chi2(gf.graph, gf.values) == pytest.approx(chi2(g, vals), rel=1e-12)
    np.testing.assert_allclose(gf.graph.block("point").information, g.block("point").information, rtol=1e-12)


def test_g2o_point_ids_shift_when_they_collide_with_pose_ids(tmp_path, rng):
    g, vals = _landmark_graph(rng)  # points 0..3 collide with poses 0..3
    p = tmp_path / "a.g2o"
    write_g2o(p, g, vals)
    assert "VERTEX_XY 40 " in p.read_text()
    gf = read_g2o(p)
    np.testing.assert_array_equal(gf.values.point_keys, np.arange(40, 44))


def test_toro_round_trip_and_frame_conversion(tmp_path, rng):
    sg = manhattan_walk(rng, num_poses=50)
    g = FactorGraph()
    b = sg.graph.block("between")
    # anisotropic, correlated information so the frame conversion matters
    om = np.array([[40.0, -8.0, 3.0], [-8.0, 300.0, 5.0], [3.0, 5.0, 900.0]])
    g.add_between(b.keys[0], b.keys[1], b.z, om)
    p = tmp_path / "a.graph"
    write_toro(p, g, sg.initial)
    gf = read_toro(p)
    assert chi2(gf.graph, gf.values) == pytest.approx(chi2(g, sg.initial), rel=1e-10)
    # chi2 with TORO's own error convention (frame of pose i) and the file's numbers equals ours
    line = next(ln for ln in p.read_text().splitlines() if ln.startswith("EDGE2")).split()
    i, j = int(line[1]), int(line[2])
    z = np.array(line[3:6], float)
    xx, xy, yy, tt, xt, yt = map(float, line[6:])
    om_t = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])
    xi, xj = sg.initial.pose(i), sg.initial.pose(j)
    c, s = np.cos(xi[2]), np.sin(xi[2])
    d = xj[:2] - xi[:2]
    e_t = np.array([c * d[0] + s * d[1] - z[0], -s * d[0] + c * d[1] - z[1],
                    np.angle(np.exp(1j * (xj[2] - xi[2] - z[2])))])
    from slam2d.graph.factors import between_error

    e = between_error(xi, xj, z)
    assert e_t @ om_t @ e_t == pytest.approx(e @ om @ e, rel=1e-9)


def test_isam_round_trip_with_separate_namespaces(tmp_path, rng):
    g, vals = _landmark_graph(rng)
    p = tmp_path / "a.txt"
    write_isam(p, g)
    gf = read_isam(p)
    assert gf.initial_guess == "spanning tree"
    np.testing.assert_array_equal(gf.values.point_keys, np.arange(4))  # overlap pose ids 0..3, kept apart
    a, sa = optimize(g, vals)
    b, sb = optimize(gf.graph, gf.values)
    assert sb.chi2_final == pytest.approx(sa.chi2_final, rel=1e-6)


def _write(tmp_path, text, name="x.g2o"):
    p = tmp_path / name
    p.write_text(text)
    return p


V = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
E = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"


@pytest.mark.parametrize("text, pattern", [
    (V + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", r"x.g2o:3: EDGE_SE2 expects 11 fields, got 10"),
    (V + "EDGE_SE2 0 1 1 0 zero 1 0 0 1 0 1\n", r"x.g2o:3: expected a number, got 'zero'"),
    (V + "EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1\n", r"x.g2o:3: expected an integer id, got '1.5'"),
    (V + "EDGE_SE2 0 1 1 0 nan 1 0 0 1 0 1\n", r"x.g2o:3: non-finite number 'nan'"),
    (V + "EDGE_SE2 0 2 1 0 0 1 0 0 1 0 1\n", r"x.g2o:3: EDGE_SE2 refers to VERTEX_SE2 2, which is not declared"),
    (V + "EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n", r"x.g2o:3: EDGE_SE2 information matrix is not positive definite"),
    (V + "VERTEX_SE2 1 0 0 0\n", r"x.g2o:3: duplicate VERTEX_SE2 id 1"),
    (V + "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1\n", r"x.g2o:3: EDGE_SE2 connects vertex 1 to itself"),
])
def test_g2o_errors_name_file_line_and_token(tmp_path, text, pattern):
    with pytest.raises(GraphFormatError, match=pattern):
        read_g2o(_write(tmp_path, text))


def test_unknown_tags_are_skipped_with_one_counted_warning(tmp_path):
    p = _write(tmp_path, V + "PARAMS_SE2OFFSET 0 0 0 0\n" + E + "PARAMS_SE2OFFSET 1 0 0 0\n# comment\n")
    with pytest.warns(GraphFormatWarning, match="PARAMS_SE2OFFSET x2"):
        gf = read_g2o(p)
    assert gf.skipped == {"PARAMS_SE2OFFSET": 2}
    assert gf.graph.num_factors == 1
    with pytest.raises(GraphFormatError, match="x.g2o:3: unknown tag 'PARAMS_SE2OFFSET'"):
        read_g2o(p, on_unknown="error")


def test_g2o_without_vertices_uses_the_spanning_tree_and_fix(tmp_path):
    p = _write(tmp_path, E + "EDGE_SE2 1 2 1 0 1.5707963267948966 1 0 0 1 0 1\nFIX 0\n")
    gf = read_g2o(p)
    assert gf.initial_guess == "spanning tree"
    np.testing.assert_allclose(gf.values.pose(2), [2, 0, np.pi / 2], atol=1e-12)
    np.testing.assert_array_equal(gf.fixed_pose_keys, [0])
    assert chi2(gf.graph, gf.values) == pytest.approx(0.0, abs=1e-20)


def test_detect_format(tmp_path):
    assert detect_format(_write(tmp_path, V, "a.g2o")) == "g2o"
    assert detect_format(_write(tmp_path, "VERTEX2 0 0 0 0\n", "a.dat")) == "toro"
    assert detect_format(_write(tmp_path, "ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\n", "b.dat")) == "isam"
    with pytest.raises(GraphFormatError, match="cannot tell"):
        detect_format(_write(tmp_path, "HELLO\n", "c.dat"))


LINE_TOKENS = st.sampled_from(["VERTEX_SE2", "VERTEX_XY", "EDGE_SE2", "EDGE_SE2_XY", "EDGE_SE2_PRIOR", "FIX",
                               "VERTEX2", "EDGE2", "ODOMETRY", "LANDMARK", "0", "1", "2", "-1", "1.5", "nan", "inf",
                               "1e400", "abc", "#", "0.5", "99999999999999999999999", "3"])
LINES = st.lists(st.lists(LINE_TOKENS, min_size=0, max_size=13).map(" ".join), max_size=12).map("\n".join)
VALID = st.sampled_from([V + E, "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n",
                         "ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK 1 0 2 0 1 0 1\n"])


@settings(max_examples=150)
@given(st.tuples(VALID, LINES, st.booleans()), st.sampled_from(["g2o", "toro", "isam"]))
def test_readers_fuzz_only_raise_the_documented_error(tmp_path_factory, case, fmt):
    valid, noise, prepend = case
    text = noise + "\n" + valid if prepend else valid + noise
    p = tmp_path_factory.mktemp("fz") / "f.txt"
    p.write_text(text)
    reader = {"g2o": read_g2o, "toro": read_toro, "isam": read_isam}[fmt]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GraphFormatWarning)
        try:
            gf = reader(p)
        except GraphFormatError:
            return
    assert np.all(np.isfinite(gf.values.poses)) and np.all(np.isfinite(gf.values.points))


def test_cli_optimize_writes_g2o_and_json(tmp_path, rng, capsys):
    sg = manhattan_walk(rng, num_poses=80)
    inp = tmp_path / "in.g2o"
    write_g2o(inp, sg.graph, sg.initial)
    out, js = tmp_path / "out.g2o", tmp_path / "s.json"
    assert main(["optimize", str(inp), "--out", str(out), "--json", str(js), "--solver", "gn"]) == 0
    rec = json.loads(js.read_text())
    for k in ("chi2_initial", "chi2_final", "iterations", "solve_s", "poses", "landmarks", "factors"):
        assert k in rec
    assert rec["poses"] == 80 and rec["landmarks"] == 0 and rec["factors"] == sg.graph.num_factors
    ref, s = optimize(sg.graph, sg.initial)
    assert rec["chi2_final"] == pytest.approx(s.chi2_final, rel=1e-6)
    gf = read_g2o(out)
    assert chi2(gf.graph, gf.values) == pytest.approx(rec["chi2_final"], rel=1e-9)
    # robust kernel with a parameter, chordal init
    assert main(["optimize", str(inp), "--out", str(out), "--robust", "cauchy:2", "--init", "chordal"]) == 0
    bad = _write(tmp_path, V + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", "bad.g2o")
    assert main(["optimize", str(bad), "--out", str(out)]) == 2
    assert "bad.g2o:3" in capsys.readouterr().err
