import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from slam2d import _jacobians
from slam2d.geometry import (
    angle_diff,
    between,
    chi2_gate,
    compose,
    covariance_ellipse,
    exp,
    inverse,
    local,
    log,
    mahalanobis_sq,
    retract,
    se2,
    transform_points,
    wrap_angle,
    wrap_angle_scalar,
)
from slam2d.graph.factors import between_error
from slam2d.testing import assert_jacobian_matches, numerical_jacobian

PAIRS = _jacobians.REGISTRY


def test_registry_covers_core_functions():
    names = {p.name.rsplit(".", 1)[-1] for p in PAIRS}
    for n in ["compose", "inverse", "between", "transform_points", "exp", "log", "odometry_predict",
              "velocity_predict", "range_bearing", "range_bearing_inverse", "bearing_only", "absolute_position"]:
        assert n in names


@pytest.mark.parametrize("edge", ["random", "zero", "pi", "-pi"])
@pytest.mark.parametrize("pair", PAIRS, ids=[p.name for p in PAIRS])
def test_registered_jacobians_match_finite_differences(pair, edge):
    rng = np.random.default_rng(7)
    kwargs = dict(pair.kwargs)
    for _ in range(5):
        args = [_jacobians.sample_arg(k, rng, edge) for k in pair.arg_kinds]
        analytic = pair.jacobians(*args, **kwargs)
        assert len(analytic) == len(args)
        for i, kind in enumerate(pair.arg_kinds):

            def f(xi, i=i, args=args):
                a = list(args)
                a[i] = xi
                return pair.function(*a, **kwargs)

            angles = _jacobians.ARG_KINDS[kind][1]
            assert_jacobian_matches(f, args[i], analytic[i], input_angles=angles, output_angles=pair.output_angles,
                                    rtol=1e-5, atol=1e-6)


def test_scalar_wrap_equals_wrap_angle():
    edges = [np.pi, -np.pi, np.nextafter(np.pi, 0), np.nextafter(-np.pi, -np.inf), 3 * np.pi, -3 * np.pi, 0.0, -0.0]
    a = np.concatenate([edges, np.random.default_rng(2).uniform(-50, 50, 2000)])
    np.testing.assert_array_equal([wrap_angle_scalar(float(x)) for x in a], wrap_angle(a))


def test_wrap_angle_boundaries_are_pinned():
    assert wrap_angle(np.pi) == -np.pi
    assert wrap_angle(-np.pi) == -np.pi
    below = np.nextafter(-np.pi, -np.inf)
    w = wrap_angle(below)
    assert -np.pi <= w < np.pi
    assert wrap_angle(3 * np.pi) == -np.pi
    assert wrap_angle(0.0) == 0.0
    a = np.linspace(-20, 20, 1001).reshape(7, 11, 13)[..., :13]
    out = wrap_angle(a)
    assert out.shape == a.shape and out.dtype == np.float64
    assert np.all(out >= -np.pi) and np.all(out < np.pi)
    np.testing.assert_allclose(np.cos(out), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(out), np.sin(a), atol=1e-12)
    np.testing.assert_array_equal(wrap_angle(out), out)


def test_angle_diff_across_the_cut():
    assert angle_diff(np.deg2rad(179), np.deg2rad(-179)) == pytest.approx(np.deg2rad(-2))
    assert angle_diff(np.deg2rad(-179), np.deg2rad(179)) == pytest.approx(np.deg2rad(2))


SHAPES = st.sampled_from([(), (1,), (3, 4)])


def poses(shape):
    xy = hnp.arrays(np.float64, shape + (2,), elements=st.floats(-50, 50))
    th = hnp.arrays(np.float64, shape + (1,), elements=st.floats(-np.pi, np.pi - 1e-9))
    return st.tuples(xy, th).map(lambda t: np.concatenate(t, axis=-1))


@st.composite
def pose_batch(draw, n=3):
    shape = draw(SHAPES)
    return [draw(poses(shape)) for _ in range(n)]


def close_poses(a, b, atol=1e-9):
    np.testing.assert_allclose(a[..., :2], b[..., :2], atol=atol)
    np.testing.assert_allclose(angle_diff(a[..., 2], b[..., 2]), 0, atol=atol)


@given(pose_batch())
def test_group_axioms(ps):
    a, b, c = ps
    identity = np.zeros_like(a)
    close_poses(compose(a, inverse(a)), identity)
    close_poses(compose(inverse(a), a), identity)
    close_poses(compose(compose(a, b), c), compose(a, compose(b, c)), atol=1e-8)
    close_poses(between(a, b), compose(inverse(a), b), atol=1e-8)
    close_poses(compose(a, between(a, b)), b, atol=1e-8)
    close_poses(retract(a, local(a, b)), b, atol=1e-8)
    d = local(a, b)
    np.testing.assert_allclose(local(a, retract(a, d)), d, atol=1e-8)


@given(pose_batch(1))
def test_exp_log_round_trip(ps):
    (a,) = ps
    close_poses(exp(log(a)), a, atol=1e-7)


def test_exp_log_near_zero_and_pi():
    for th in [0.0, 1e-9, -1e-6, np.pi - 1e-6, -np.pi + 1e-9]:
        p = np.array([1.3, -0.4, th])
        close_poses(exp(log(p)), p, atol=1e-8)


@given(pose_batch(2))
def test_batched_equals_loop(ps):
    a, b = ps
    batched = compose(a, b)
    flat_a, flat_b = a.reshape(-1, 3), b.reshape(-1, 3)
    looped = np.array([compose(x, y) for x, y in zip(flat_a, flat_b, strict=True)]).reshape(batched.shape)
    np.testing.assert_array_equal(batched, looped)
    pts = flat_a[:, :2]
    tp = transform_points(flat_b, pts)
    np.testing.assert_allclose(tp, np.array([transform_points(p, q) for p, q in zip(flat_b, pts, strict=True)]))


def test_numerical_jacobian_of_linear_map_is_exact():
    m = np.array([[1.0, 2.0], [3.0, -4.0], [0.5, 0.0]])
    j = numerical_jacobian(lambda x: m @ x, np.array([0.3, -0.2]))
    np.testing.assert_allclose(j, m, atol=1e-9)


def test_mahalanobis_and_gate():
    s = np.array([[4.0, 0.0], [0.0, 1.0]])
    assert mahalanobis_sq(np.array([2.0, 1.0]), s) == pytest.approx(2.0)
    batch = mahalanobis_sq(np.ones((5, 2)), np.broadcast_to(s, (5, 2, 2)))
    assert batch.shape == (5,)
    with pytest.raises(np.linalg.LinAlgError):
        mahalanobis_sq(np.ones(2), np.array([[1.0, 0.0], [0.0, -1.0]]))
    assert chi2_gate(0.95, 2) == pytest.approx(5.991, abs=1e-3)
    assert chi2_gate(0.99, 1) == pytest.approx(6.635, abs=1e-3)
    # monte-carlo: the 95% gate accepts ~95% of correct 2-dof residuals
    r = np.random.default_rng(0).standard_normal((20000, 2))
    acc = np.mean(np.sum(r * r, axis=1) < chi2_gate(0.95, 2))
    assert 0.94 < acc < 0.96
    with pytest.raises(ValueError):
        chi2_gate(1.5, 2)


def test_covariance_ellipse():
    e = covariance_ellipse(np.diag([4.0, 1.0]), probability=0.95)
    k = np.sqrt(chi2_gate(0.95, 2))
    assert e.semi_major == pytest.approx(2 * k)
    assert e.semi_minor == pytest.approx(k)
    assert e.angle == pytest.approx(0.0)
    r = np.array([[np.cos(0.5), -np.sin(0.5)], [np.sin(0.5), np.cos(0.5)]])
    e2 = covariance_ellipse(r @ np.diag([4.0, 1.0]) @ r.T)
    assert e2.angle == pytest.approx(0.5)


def test_compose_chain_equals_sequential_composition():
    rng = np.random.default_rng(7)
    start = np.array([1.0, -2.0, 3.0])
    u = np.column_stack([rng.normal(0.5, 0.3, 200), rng.normal(0, 0.1, 200), rng.normal(0, 0.3, 200)])
    seq = [start]
    for ui in u:
        seq.append(se2.compose(seq[-1], ui))
    got = se2.compose_chain(start, u)
    assert got.shape == (201, 3)
    np.testing.assert_allclose(got[:, :2], np.array(seq)[:, :2], atol=1e-9)
    np.testing.assert_allclose(angle_diff(got[:, 2], np.array(seq)[:, 2]), 0.0, atol=1e-9)


def test_a_start_frame_covariance_turned_into_the_between_frame_weighs_every_displacement_as_before():
    """An ICP result T_i_j with covariance C over [x, y, theta] in pose i's frame enters a between factor, whose
    error is turned by T's angle: with the information turned by covariance_in_frame, the factor's chi-square of
    any displacement of j (in i's frame) equals that displacement's Mahalanobis distance under C. Without the turn
    a corridor's long axis would be weighed as its short one after a 90-degree turn."""
    rng = np.random.default_rng(3)
    cov = np.diag([0.04**2, 0.002**2, 0.001**2])  # a corridor along i's x: long along it, sure across
    for th in (0.0, 0.7, np.pi / 2, -2.5, np.pi):
        z = np.array([1.0, -0.4, th])
        info = se2.covariance_in_frame(np.linalg.inv(cov), th)
        np.testing.assert_allclose(info, np.linalg.inv(se2.covariance_in_frame(cov, th)), rtol=1e-9)
        for d in rng.normal(0.0, 0.02, (20, 3)):
            e = between_error(np.zeros(3), z + d, z)
            assert e @ info @ e == pytest.approx(d @ np.linalg.inv(cov) @ d, rel=1e-9)
        if abs(np.sin(th)) > 0.5:  # unturned, one sigma along the corridor weighs as ten across it, or more
            e = between_error(np.zeros(3), z + [0.04, 0.0, 0.0], z)
            assert e @ np.linalg.inv(cov) @ e > 10.0


def test_matrix_from_rows_broadcasts_scalars_and_arrays_like_a_stack():
    rng = np.random.default_rng(3)
    c, x = rng.normal(size=(4, 1)), rng.normal(size=5)  # broadcast to (4, 5)
    m = se2.matrix_from_rows([c, 0.0, x], [1.0, c * x, -c])
    shape = (4, 5)
    want = np.stack([np.stack([np.broadcast_to(e, shape) for e in r], axis=-1)
                     for r in ([c, 0.0, x], [1.0, c * x, -c])], axis=-2)
    assert m.shape == (4, 5, 2, 3) and m.dtype == np.float64 and np.array_equal(m, want)
    with pytest.raises(ValueError, match="different lengths"):
        se2.matrix_from_rows([c, x], [c])
