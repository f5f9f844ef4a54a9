"""Rules of the estimator contract and of module size, checked by scanning src/ (issue 15).

* results are typed fields of ``Estimate``, never looked up by string: no ``extras[...]`` / ``.extras``;
* optional abilities are protocols checked with ``isinstance``/``require``: no ``hasattr(`` anywhere and no
  ``getattr(`` on an estimator (``getattr(est...``, ``getattr(self.est...``); ``getattr`` over a dataclass's own
  fields (``getattr(self, name)``) stays allowed;
* every page and command is built: no "not available yet" placeholder text;
* small modules: no file in src/ over 600 lines.

Files still being reworked by other helpers are listed explicitly below with a non-strict xfail; drop an entry
once its file complies (the xfail is not strict, so a file that already complies just shows as XPASS).
"""

import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "slam2d"
TEXT_SUFFIXES = {".py", ".html", ".js", ".css", ".md"}
FILES = sorted(p for p in SRC.rglob("*") if p.is_file() and p.suffix in TEXT_SUFFIXES)
MAX_LINES = 600

RULES = {
    "results looked up by string (extras)": re.compile(r"\bextras\s*\[|\.extras\b"),
    "ability probed with hasattr": re.compile(r"\bhasattr\s*\("),
    "ability probed with getattr on an estimator": re.compile(r"\bgetattr\s*\(\s*(self\.)?_?est(imator)?\b"),
    "placeholder text": re.compile(r"not available yet", re.IGNORECASE),
}

#: files other helpers are splitting right now (issue 15); remove each entry once the file is under the limit
PENDING_SPLIT: set[str] = set()
#: files that still carry the lab's old "not available yet" notices for optional back ends (all back ends exist
#: now; the web/cli owners remove these paths); remove each entry once the text is gone
PENDING_PLACEHOLDERS: set[str] = set()


def _rel(p: Path) -> str:
    return p.relative_to(SRC).as_posix()


def _params(files: list[Path], pending: set[str], reason: str) -> list:
    return [pytest.param(p, id=_rel(p), marks=[pytest.mark.xfail(strict=False, reason=reason)]
                         if _rel(p) in pending else []) for p in files]


def test_the_scan_sees_the_package():
    names = {_rel(p) for p in FILES}
    assert {"estimator.py", "graph/online.py", "web/sessions/sim.py"} <= names
    assert all(n in names for n in PENDING_SPLIT | PENDING_PLACEHOLDERS), "stale entry: the file no longer exists"


@pytest.mark.parametrize("rule", ["results looked up by string (extras)", "ability probed with hasattr",
                                  "ability probed with getattr on an estimator"])
def test_no_string_lookups_or_ability_probes(rule):
    pattern = RULES[rule]
    hits = [f"{_rel(p)}:{i}: {line.strip()}" for p in FILES
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if pattern.search(line)]
    assert hits == [], f"{rule}:\n" + "\n".join(hits)


@pytest.mark.parametrize("path", _params(FILES, PENDING_PLACEHOLDERS, "placeholder notices still being removed"))
def test_no_placeholder_text(path):
    hits = [i for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
            if RULES["placeholder text"].search(line)]
    assert hits == [], f"{_rel(path)} lines {hits}: 'not available yet'"


@pytest.mark.parametrize("path", _params([p for p in FILES if p.suffix == ".py"], PENDING_SPLIT,
                                          "being split by another helper (issue 15)"))
def test_no_module_over_600_lines(path):
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_LINES, f"{_rel(path)} has {n} lines (limit {MAX_LINES})"


def test_the_rules_catch_what_they_forbid():
    """Each pattern matches the forms it is meant to forbid and spares the allowed ones."""
    bad = {
        "results looked up by string (extras)": ["snap.extras['loops']", "e = est.extras"],
        "ability probed with hasattr": ["if hasattr(est, 'graph_view'):"],
        "ability probed with getattr on an estimator": ["getattr(est, 'save_map', None)",
                                                        "getattr(self.estimator, 'loops')", "getattr(self._est, 'x')"],
        "placeholder text": ["'Not available yet: x'"],
    }
    good = ["getattr(self, name)", "getattr(cfg, f.name)", "getattr(estimate, field.name)", "extras_count = 0"]
    for rule, lines in bad.items():
        assert all(RULES[rule].search(s) for s in lines), rule
        assert not any(RULES[rule].search(s) for s in good), rule
