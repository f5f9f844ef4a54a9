"""Server-side pieces without a browser: frame format, parameter validation, sessions' numbers."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from slam2d.estimator import Estimate, GraphView
from slam2d.eval.trajectory import ate
from slam2d.models.sensors import range_bearing_inverse, range_bearing_inverse_jacobians
from slam2d.web.app import MAX_COMMAND_BYTES, parse_command
from slam2d.web.frames import HEADER, MAGIC, decode_frame, encode_frame
from slam2d.web.pages import PAGE_BY_SLUG, PAGES
from slam2d.web.params import CommandError, Param
from slam2d.web.sessions import (
    AssociationSession,
    FeaturesSession,
    GraphSession,
    SimSession,
    abs_correlation,
    graph_view_sections,
    observation_covariances,
)


def test_frame_round_trip_and_alignment(rng: np.random.Generator) -> None:
    a = rng.standard_normal((7, 3))
    b = rng.standard_normal((1, 4))
    buf = encode_frame(41, [("TPTH", a), ("PCOV", b[0]), ("EMPT", np.zeros((0, 2)))])
    assert buf[:4] == MAGIC and len(buf) == HEADER.size + 3 * 16 + 4 * (21 + 4)
    seq, sec = decode_frame(buf)
    assert seq == 41
    np.testing.assert_array_equal(sec["TPTH"], a.astype(np.float32))
    np.testing.assert_array_equal(sec["PCOV"], b.astype(np.float32))
    assert sec["EMPT"].shape == (0, 2)
    # every section payload starts at a multiple of 4 (Float32Array views need it)
    off = HEADER.size
    for arr in (a, b, np.zeros((0, 2))):
        assert off % 4 == 0
        off += 16 + 4 * arr.size
    with pytest.raises(ValueError, match="tag"):
        encode_frame(0, [("TOOLONG", a)])
    with pytest.raises(ValueError, match="not a slam2d frame"):
        decode_frame(buf[:-4])


def test_param_validation() -> None:
    f = Param("x", "x", "float", 1.0, lo=0.0, hi=2.0)
    assert f.coerce(1.5) == 1.5 and f.coerce(2) == 2.0
    for bad in (3.0, -0.1, float("nan"), float("inf"), "1", True, None, [1]):
        with pytest.raises(CommandError, match="'x'"):
            f.coerce(bad)
    i = Param("n", "n", "int", 1, lo=0, hi=10)
    assert i.coerce(3.0) == 3 and isinstance(i.coerce(3.0), int)
    with pytest.raises(CommandError):
        i.coerce(2.5)
    c = Param("m", "m", "choice", "a", choices=("a", "b"))
    assert c.coerce("b") == "b"
    with pytest.raises(CommandError, match="one of"):
        c.coerce("z")
    b = Param("p", "p", "bool", False)
    assert b.coerce(True) is True
    with pytest.raises(CommandError):
        b.coerce(1)


def test_parse_command_rejects_junk() -> None:
    assert parse_command('{"type": "ping"}') == {"type": "ping"}
    for bad in (None, b"{}", "nope", "[]", "1", "x" * (MAX_COMMAND_BYTES + 1), "[" * 3000):
        with pytest.raises(CommandError):
            parse_command(bad)


def test_session_commands_are_validated_and_never_half_applied() -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)
    before = dict(s.values)
    for bad in ({"type": "param", "name": "sensor_range_m", "value": 0.0}, {"type": "param", "name": "zzz"},
                {"type": "param", "name": "estimator", "value": "no-such"}, {"type": "key", "key": "a", "down": True},
                {"type": "key", "key": "ArrowUp", "down": "yes"}, {"type": "action", "name": "explode"}, {}):
        with pytest.raises(CommandError):
            s.apply(bad)
    assert s.values == before


def test_keys_drive_the_simulator_and_numbers_come_from_the_library(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("slam2d.web.sessions.sim.STEP_BUDGET_S", float("inf"))  # a loaded machine must not cut steps
    s = PAGE_BY_SLUG["simulator"].make(2)
    assert isinstance(s, SimSession)
    start = s.sim.pose.copy()
    s.apply({"type": "key", "key": "ArrowUp", "down": True})
    s.advance(1.0)  # 1 s at 10 steps/s
    assert s.sim.index == 8  # capped: a stall never bursts more than 8 steps
    moved = s.sim.pose[:2] - start[:2]
    assert np.hypot(*moved) == pytest.approx(8 * float(s.sim.config.dt_s) * float(s.sim.config.speed_mps))
    s.apply({"type": "key", "key": "ArrowUp", "down": False})
    nums = s.numbers()
    assert nums["ate_rmse_m"] == pytest.approx(ate(np.asarray(s.est_path), np.asarray(s.true_path)).rmse_m)
    assert nums["state_dim"] == s.snap.state_dim
    assert nums["step"] == 8


def test_reset_replays_the_same_run_and_seed_changes_it() -> None:
    s = PAGE_BY_SLUG["simulator"].make(1)
    s.apply({"type": "param", "name": "drive", "value": "explore"})
    for _ in range(30):
        s.apply({"type": "action", "name": "step"})
    a = s.snap.pose.copy()
    s.apply({"type": "action", "name": "reset"})
    for _ in range(30):
        s.apply({"type": "action", "name": "step"})
    np.testing.assert_array_equal(s.snap.pose, a)
    s.apply({"type": "param", "name": "seed", "value": 2})
    for _ in range(30):
        s.apply({"type": "action", "name": "step"})
    assert not np.allclose(s.snap.pose, a)


def test_sensor_range_changes_what_the_simulator_reports() -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)
    s.apply({"type": "param", "name": "sensor_range_m", "value": 2.0})
    s.apply({"type": "action", "name": "step"})
    assert s.last_step is not None
    near = len(s.last_step.observations)
    s.apply({"type": "param", "name": "sensor_range_m", "value": 50.0})
    s.apply({"type": "action", "name": "step"})
    assert len(s.last_step.observations) > near
    assert np.all(s.last_step.observations.range_m <= 50.0 + 1.0)


def test_observation_covariances_match_the_inverse_model_jacobian(rng: np.random.Generator) -> None:
    pose = np.array([1.0, -2.0, 0.7])
    z = np.column_stack([rng.uniform(1, 10, 5), rng.uniform(-3, 3, 5)])
    r = np.diag([0.1**2, 0.02**2])
    covs = observation_covariances(pose, z, r)
    for k in range(5):
        _, gz = range_bearing_inverse_jacobians(pose, z[k])
        np.testing.assert_allclose(covs[k], gz @ r @ gz.T, atol=1e-15)
        # independent check: sample the sensor noise and push it through the inverse model
    samples = z[0] + rng.standard_normal((20000, 2)) * np.sqrt(np.diag(r))
    emp = np.cov(range_bearing_inverse(np.broadcast_to(pose, (20000, 3)), samples).T)
    np.testing.assert_allclose(emp, covs[0], rtol=0.1, atol=1e-5)


def test_abs_correlation_is_exact_when_small_and_block_averaged_when_large(rng: np.random.Generator) -> None:
    a = rng.standard_normal((6, 6))
    cov = a @ a.T + np.eye(6)
    corr = abs_correlation(cov)
    d = np.sqrt(np.diag(cov))
    np.testing.assert_allclose(corr, np.abs(cov) / np.outer(d, d))
    assert np.allclose(np.diag(corr), 1.0)
    big = np.eye(200)
    small = abs_correlation(big, limit=50)
    assert small.shape == (50, 50)
    np.testing.assert_allclose(np.diag(small), 0.25)  # 4x4 blocks of the identity: 4 ones out of 16
    np.testing.assert_allclose(small.sum(), 200 / 16)


def test_association_known_oracle_is_perfect_and_counts_are_consistent() -> None:
    s = AssociationSession(seed=3)
    s.apply({"type": "param", "name": "method", "value": "known"})
    nums = s.numbers()
    assert nums["observations"] == len(s.obs) > 0
    assert nums["wrong"] == 0 and nums["precision"] == 1.0
    assert nums["matched"] + nums["new_or_clutter"] == nums["observations"]
    # scramble draws a new scene from the session's own generator
    old = s.landmarks.copy()
    s.apply({"type": "action", "name": "scramble"})
    assert not np.array_equal(old, s.landmarks)


def test_a_failing_estimator_is_reported_not_fatal(monkeypatch: pytest.MonkeyPatch) -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)

    class Broken:
        def step(self, step: object) -> None:
            raise FloatingPointError("singular matrix")

        def estimate(self) -> Estimate:
            return Estimate(pose=np.zeros(3))

    s.est = Broken()  # type: ignore[assignment]
    s.apply({"type": "action", "name": "step"})
    assert s.values["paused"] is True
    assert any("singular matrix" in n for n in s.notices)
    s.advance(1.0)  # stays stopped; the frame still encodes
    encode_frame(0, s.sections())


@pytest.mark.parametrize("page", [p.slug for p in PAGES])
def test_every_page_session_builds_and_draws(page: str) -> None:
    s = PAGE_BY_SLUG[page].make(0)
    hello = s.hello()
    assert hello["type"] == "hello" and hello["page"] == page
    s.advance(0.5)
    seq, sec = decode_frame(encode_frame(0, s.sections()))
    assert sec["NUMS"].shape == (1, len(s.scalars))
    assert hello["notices"] == []  # every page's back end exists: nothing to excuse
    assert set(hello["labels"]) == set(s.scalars) and set(hello["rows"]) <= set(s.scalars)


def test_particle_slider_reaches_the_estimator_config_when_it_has_one() -> None:
    s = PAGE_BY_SLUG["fastslam"].make(0)
    assert isinstance(s, SimSession)
    assert s.values["estimator"] == "fastslam"
    s.apply({"type": "param", "name": "particles", "value": 7})
    assert s.est.config.particles == 7  # type: ignore[attr-defined]
    assert s.snap.particles is not None and len(s.snap.particles.poses) == 7
    s.apply({"type": "param", "name": "estimator", "value": "ekf"})
    assert s.state()["inactive"] == ["particles"]  # the page greys the slider out: it changes nothing for the EKF
    assert "n_eff" not in s.rows() and "particles" not in s.rows()


def test_break_it_toggles_damage_what_the_estimator_is_told() -> None:
    s = PAGE_BY_SLUG["loop"].make(0)
    assert isinstance(s, SimSession)
    s.apply({"type": "param", "name": "paused", "value": True})
    s.apply({"type": "param", "name": "few_landmarks", "value": True})
    s.apply({"type": "param", "name": "wrong_association", "value": True})
    told, seen = 0, 0
    wrong = 0
    for _ in range(40):
        s.apply({"type": "action", "name": "step"})
        assert s.last_step is not None
        ids = s.last_step.observations.landmark_id
        told += int((ids >= 0).sum())
        # the kept fifth: every id the estimator hears belongs to a kept landmark or is a wrong-but-valid id
        assert np.all(np.isin(ids[ids >= 0], s.sim.world.landmark_ids))
        true_ids = s.sim.to_log().obs_id[s.sim.to_log().obs_step == s.sim.index]
        seen += int((true_ids >= 0).sum())
        kept_true = true_ids[np.isin(true_ids, s.kept_ids)]
        assert len(kept_true) == int((ids >= 0).sum())
        wrong += int((np.sort(ids[ids >= 0]) != np.sort(kept_true)).any())
    assert 0 < told < seen  # only a fifth of the landmarks report
    assert wrong > 0  # and some of their ids are wrong


def test_an_estimator_that_cannot_start_falls_back_with_a_notice(monkeypatch: pytest.MonkeyPatch) -> None:
    from slam2d.filters.dead_reckoning import DeadReckoningConfig
    from slam2d.lab import registry

    def factory(cfg: object) -> object:
        raise RuntimeError("not ready")

    monkeypatch.setitem(registry.ESTIMATORS, "broken",
                        registry.EstimatorSpec("broken", DeadReckoningConfig, factory, "test"))  # type: ignore[arg-type]
    s = SimSession(page="simulator", title="t", estimator="broken", controls=("estimator",))
    assert s.values["estimator"] == "dead-reckoning"
    assert any("'broken' could not be started" in n and "not ready" in n for n in s.notices)
    s.advance(0.3)
    assert s.sim.index >= 1


def test_features_page_threshold_controls_the_detector() -> None:
    s = FeaturesSession(seed=0)
    counts = []
    for t in (0.01, 0.1, 0.5, 0.9):
        s.apply({"type": "param", "name": "threshold_rel", "value": t})
        counts.append(len(s.detected))
        assert 0.0 <= s.score.precision <= 1.0 and 0.0 <= s.score.recall <= 1.0
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[-1]
    _, sec = decode_frame(encode_frame(0, s.sections()))
    assert sec["FEAT"].shape == (counts[-1], 2) and sec["NUMS"][0, 0] == counts[-1]


def test_maps_page_occupancy_layer_fills_from_scans() -> None:
    s = PAGE_BY_SLUG["maps"].make(0)
    s.apply({"type": "param", "name": "layer", "value": "occupancy"})
    for _ in range(10):
        s.advance(0.5)
    _, sec = decode_frame(encode_frame(0, s.sections()))
    p = sec["GRID"]
    assert (p > 0.65).any() and (p < 0.35).any()  # walls seen as occupied, the space in between as free
    assert sec["GRDM"].shape == (1, 3)


def test_graph_page_optimises_the_drive_and_reports_sparsity() -> None:
    s = GraphSession(seed=1)
    s.apply({"type": "param", "name": "steps", "value": 60})
    for _ in range(20):
        s.advance(0.5)
    assert s.sim.index == 60
    s.apply({"type": "action", "name": "optimize"})
    costs = []
    for _ in range(60):
        s.advance(0.5)
        costs.append(s.cost)
        if s.converged:
            break
    assert s.converged and s.iteration >= 2
    assert all(b <= a * (1 + 1e-9) for a, b in itertools.pairwise(costs[1:]))  # GN descends here
    nums = dict(zip(s.scalars, decode_frame(encode_frame(0, s.sections()))[1]["NUMS"][0].tolist(), strict=True))
    assert nums["ate_now_m"] < nums["ate_initial_m"]
    # Omega: chain of poses + pose-landmark blocks; far from dense
    assert 0 < nums["omega_nonzero_blocks"] < 0.5 * nums["omega_blocks"]


def test_maps_page_topology_layer_has_places_and_connections() -> None:
    s = PAGE_BY_SLUG["maps"].make(0)
    s.apply({"type": "param", "name": "layer", "value": "topology"})
    for _ in range(30):
        s.advance(0.5)
    s.sections()
    _, sec = decode_frame(encode_frame(0, s.sections()))
    nums = dict(zip(s.scalars, sec["NUMS"][0].tolist(), strict=True))
    assert nums["places"] >= 2 and nums["connections"] >= 1
    assert sec["GNOD"].shape == (nums["places"], 2) and sec["GEDG"].shape == (nums["connections"], 4)


def test_graph_view_edges_join_the_right_variables() -> None:
    view = GraphView(poses=np.array([[0.0, 0, 0], [1, 0, 0], [2, 1, 0]]), pose_keys=np.array([10, 5, 7]),
                     points=np.array([[4.0, 4.0]]), point_keys=np.array([3]),
                     edges={"between": np.array([[10, 5], [5, 7]]), "range_bearing": np.array([[7, 3]]),
                            "prior": np.array([[10]])})
    sec = dict(graph_view_sections(view))
    np.testing.assert_array_equal(sec["GEDG"], [[0, 0, 1, 0], [1, 0, 2, 1], [2, 1, 4, 4]])
    view = dataclasses.replace(view, edges={"between": np.array([[10, 99]])})
    with pytest.raises(KeyError):
        graph_view_sections(view)


def test_close_loop_button_explains_when_the_estimator_cannot() -> None:
    s = PAGE_BY_SLUG["loop"].make(0)
    assert ("close_loop", "close loop now") in s.actions
    s.apply({"type": "param", "name": "estimator", "value": "dead-reckoning"})
    s.apply({"type": "action", "name": "step"})
    s.apply({"type": "action", "name": "close_loop"})
    assert any("cannot close loops" in n for n in s.notices)


def test_no_soft_imports_or_excuses_in_the_web_package() -> None:
    """Imports are hard (a broken module fails every web test instead of showing a notice), and no page excuses
    itself for a back end that exists."""
    from pathlib import Path

    import slam2d.web

    root = Path(slam2d.web.__file__).parent
    for path in [*root.rglob("*.py"), *root.rglob("*.html"), *root.rglob("*.js")]:
        text = path.read_text()
        for banned in ("not available yet", "importlib", "optional_module", "optional_attr", "getattr("):
            assert banned not in text, f"{path.relative_to(root)} contains {banned!r}"
        if path.suffix == ".py":
            assert len(text.splitlines()) < 600, f"{path.relative_to(root)} is over 600 lines"


def test_holding_an_arrow_into_a_wall_stops_the_robot_on_every_world() -> None:
    for scenario in ("room", "grid"):  # a walled world, and an open one fenced by its bounds
        s = PAGE_BY_SLUG["simulator"].make(0)
        s.apply({"type": "param", "name": "scenario", "value": scenario})
        s.apply({"type": "param", "name": "paused", "value": True})
        s.apply({"type": "key", "key": "ArrowUp", "down": True})
        xs = []
        for _ in range(600):
            s.apply({"type": "action", "name": "step"})
            xs.append(float(s.sim.pose[0]))
        x0, y0, x1, y1 = s.sim.world.bounds
        assert xs[-1] == xs[-100] and x0 <= min(xs) and max(xs) <= x1, scenario  # stopped, inside the world
        assert s.sim.collisions >= 100


def test_close_loop_now_bends_the_path_and_lowers_the_ate() -> None:
    s = PAGE_BY_SLUG["loop"].make(0)
    assert s.values["loop_closure"] is False and s.values["motion_noise"] == 4.0  # the page's defaults
    s.apply({"type": "param", "name": "paused", "value": True})
    prompted_at = None
    for i in range(470):  # once round the block and past the start
        s.apply({"type": "action", "name": "step"})
        if prompted_at is None and any(n.startswith("try this: you are back") for n in s.notices):
            prompted_at = i
    assert isinstance(s, SimSession)
    # the page noticed the return and pointed at the button, near the end of the lap, not before
    assert prompted_at is not None and prompted_at > 300, prompted_at
    before, ate_before = s.trajectory().copy(), s.ate_rmse()
    s.apply({"type": "action", "name": "close_loop"})
    assert any("accepted" in n for n in s.notices), s.notices
    after = s.trajectory()
    assert np.abs(after - before).max() > 0.3  # the correction spread along the path
    assert s.ate_rmse() < 0.7 * ate_before
    assert s.ate_rmse() == pytest.approx(ate(after, np.asarray(s.true_path)).rmse_m)
    sec = dict(s.sections())
    np.testing.assert_allclose(sec["GHST"], before[:, :2])  # the ghost is the path before the correction


@pytest.mark.parametrize("slug", [p.slug for p in PAGES])
def test_every_chapter_has_a_check_question_with_feedback(slug: str) -> None:
    from slam2d.web.checks import CHECKS

    s = PAGE_BY_SLUG[slug].make(0)
    check = CHECKS[slug]
    hello = s.hello()
    assert hello["check"] == {"question": check.question, "choices": list(check.choices)}  # never the answer
    right = s.apply({"type": "answer", "choice": check.answer})
    assert right is not None and right["correct"] is True and right["message"]
    messages = {right["message"]}
    for wrong in (i for i in range(len(check.choices)) if i != check.answer):
        reply = s.apply({"type": "answer", "choice": wrong})
        assert reply is not None and reply["correct"] is False
        messages.add(reply["message"])
    assert len(messages) == len(check.choices)  # each answer gets its own explanation
    for bad in (-1, len(check.choices), 0.5, True, "0", None):
        with pytest.raises(CommandError, match="choice"):
            s.apply({"type": "answer", "choice": bad})


def test_features_image_holds_every_wall_and_the_threshold_matters_at_default_noise() -> None:
    s = FeaturesSession(seed=0)
    counts = {}
    for t in (0.1, 0.6):
        s.apply({"type": "param", "name": "threshold_rel", "value": t})
        counts[t] = len(s.detected)
    assert counts[0.1] > counts[0.6]  # the issue-19 complaint: nothing changed between 0.1 and 0.6
    s.apply({"type": "param", "name": "image_noise", "value": 0.0})
    s.apply({"type": "param", "name": "threshold_rel", "value": 0.3})
    assert s.score.recall == 1.0 and s.score.precision == 1.0  # all eight corners: no wall is cut off the image


def test_sensor_range_circle_follows_the_robot_and_the_slider() -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)
    s.apply({"type": "param", "name": "sensor_range_m", "value": 3.5})
    sec = dict(s.sections())
    np.testing.assert_allclose(sec["RNGE"], [*s.sim.pose[:2], 3.5])
    assert "RNGE" not in dict(PAGE_BY_SLUG["drift"].make(0).sections())  # no range control, no circle


def test_simulator_graph_view_toggle_draws_the_back_ends_graph() -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)
    assert "view" in s.state()["inactive"]  # the EKF has no graph
    s.apply({"type": "param", "name": "estimator", "value": "graph"})
    s.apply({"type": "param", "name": "paused", "value": True})
    s.apply({"type": "param", "name": "drive", "value": "route"})
    for _ in range(20):
        s.apply({"type": "action", "name": "step"})
    assert "GEDG" not in dict(s.sections())
    s.apply({"type": "param", "name": "view", "value": "graph"})
    assert "view" not in s.state()["inactive"]
    sec = dict(s.sections())
    assert len(sec["GNOD"]) == 21 and len(sec["GEDG"]) >= 20  # a node per pose, at least the odometry chain


def test_simulator_runs_the_lidar_back_end_and_draws_its_occupancy_grid() -> None:
    from slam2d.graph.lidar import LidarSLAM
    from slam2d.web.sessions.sim import LIDAR_EVERY, LIDAR_GRID_EVERY

    s = PAGE_BY_SLUG["simulator"].make(0)
    s.apply({"type": "param", "name": "paused", "value": True})
    s.apply({"type": "param", "name": "drive", "value": "route"})
    s.apply({"type": "param", "name": "estimator", "value": "lidar"})
    assert isinstance(s.est, LidarSLAM) and s.sim.config.lidar.enabled and s.sim.config.lidar.every == LIDAR_EVERY
    assert any(f"every {LIDAR_EVERY} steps" in n for n in s.notices)
    for _ in range(2 * LIDAR_GRID_EVERY):
        s.apply({"type": "action", "name": "step"})
    sec = dict(s.sections())
    built_at, prob, meta = s._grid  # type: ignore[misc]
    assert built_at == 2 * LIDAR_GRID_EVERY
    ref = s.est.occupancy_grid(float(meta[2]))  # the back end's own map, at the page's resolution
    np.testing.assert_array_equal(sec["GRID"], ref.probability())
    np.testing.assert_allclose(sec["GRDM"], [*ref.origin, ref.resolution], rtol=1e-12)
    assert (prob > 0.65).any() and (prob < 0.35).any()  # walls occupied, the room between free
    s.apply({"type": "action", "name": "step"})
    assert s._grid[0] == built_at  # type: ignore[index]  # not rebuilt every step
    # a world without walls: the lidar back end is refused with a message, the page carries on
    s.apply({"type": "param", "name": "scenario", "value": "grid"})
    assert s.values["estimator"] == "dead-reckoning" and any("room or warehouse" in n for n in s.notices)
    s.apply({"type": "action", "name": "step"})
    assert "GRID" not in dict(s.sections())


def test_downsample_keeps_the_rows_already_sent_while_a_path_grows() -> None:
    from slam2d.web.sessions.base import downsample

    pts = np.arange(10_000, dtype=np.float64)[:, None] * [1.0, 2.0]
    assert len(downsample(pts[:40], 50)) == 40  # short paths go as they are
    prev = None
    for n in range(45, 3000, 7):
        d = downsample(pts[:n], 50)
        assert 2 <= len(d) <= 50 and np.array_equal(d[0], pts[0]) and np.array_equal(d[-1], pts[n - 1])
        stride = d[1, 0] - d[0, 0]
        assert stride > 0 and int(stride) & (int(stride) - 1) == 0  # a power of two
        assert np.all(np.diff(d[:-1, 0]) == stride)
        if prev is not None and prev[1] == stride:  # same stride: what was sent (but the newest row) is still there
            assert np.array_equal(d[: len(prev[0]) - 1], prev[0][:-1])
        prev = (d, stride)
