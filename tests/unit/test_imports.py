import subprocess
import sys

CORE = [
    "slam2d", "slam2d.geometry", "slam2d.models", "slam2d.sim", "slam2d.filters", "slam2d.eval", "slam2d.lab",
    "slam2d.log", "slam2d.config", "slam2d.testing",
]
FACES = ["matplotlib", "fastapi", "starlette", "uvicorn", "tqdm.rich", "rich", "typer"]


def test_core_packages_load_no_plotting_or_web_framework():
    code = (
        "import importlib, sys\n"
        f"for m in {CORE!r}: importlib.import_module(m)\n"
        f"bad = [m for m in {FACES!r} if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"core import pulled in: {out}"
