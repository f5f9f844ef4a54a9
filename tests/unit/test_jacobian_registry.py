"""The finite-difference check covers one explicit list, whatever was imported before it."""

import importlib
import inspect
import subprocess
import sys

from slam2d import _jacobians

EXPECTED = {
    "slam2d.geometry.se2": {"compose", "inverse", "between", "transform_points", "inverse_transform_points", "exp",
                            "log"},
    "slam2d.models.motion": {"rtr_to_odometry", "odometry_predict", "odometry_scalar", "velocity_increment",
                             "velocity_predict"},
    "slam2d.models.sensors": {"range_bearing", "range_bearing_scalar", "range_bearing_elementwise",
                              "range_bearing_inverse", "bearing_only", "range_only", "absolute_position"},
    "slam2d.models.floor_markers": {"marker_in_robot"},
    "slam2d.graph.factors": {f"{k}_error" for k in ("between", "prior", "point", "range_bearing", "bearing", "range",
                                                    "position", "point_prior", "pose_range_bearing")},
}
EXPECTED_NAMES = {f"{m}.{f}" for m, fs in EXPECTED.items() for f in fs}


def test_registry_is_the_expected_explicit_set():
    names = [p.name for p in _jacobians.registry()]
    assert len(names) == len(set(names)) == 29
    assert set(names) == EXPECTED_NAMES


def test_fresh_interpreter_checks_the_same_set():
    code = "from slam2d import _jacobians; print('\\n'.join(sorted(p.name for p in _jacobians.REGISTRY)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == sorted(EXPECTED_NAMES)


def test_every_public_jacobians_function_is_listed():
    """A new ``f_jacobians`` beside ``f`` in a listed module must be added to the list."""
    listed = {p.name for p in _jacobians.registry()}
    for module in EXPECTED:
        mod = importlib.import_module(module)
        for name, fn in inspect.getmembers(mod, inspect.isfunction):
            if fn.__module__ != module or not name.endswith("_jacobians") or name.startswith("_"):
                continue
            base = name.removesuffix("_jacobians")
            assert f"{module}.{base}" in listed, f"{module}.{name} is not in slam2d._jacobians.PAIRS"
