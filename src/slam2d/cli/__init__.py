"""The ``slam2d`` command line: argument parsing and printing only; every number comes from the library."""

from slam2d.cli.main import main as main
