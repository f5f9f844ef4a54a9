"""Controls a page may change: each is a typed, bounded parameter, and every browser command is validated here.

The browser builds its controls from the ``describe()`` of each parameter (sent in the session's hello message),
so a control on screen always corresponds to a validated parameter on the server.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal


class CommandError(ValueError):
    """A browser command that cannot be applied; the message is sent back to the page, the session lives on."""


@dataclass(frozen=True)
class Param:
    """One control: a float/int slider, a checkbox or a choice list."""

    name: str
    label: str
    kind: Literal["float", "int", "bool", "choice"]
    default: Any
    lo: float = 0.0
    hi: float = 1.0
    step: float = 0.0
    choices: tuple[str, ...] = field(default_factory=tuple)
    live: bool = True
    """False: changing it restarts the session (same seed) because the estimator must know the new value."""
    help: str = ""

    def coerce(self, value: Any) -> Any:
        """The validated value; CommandError naming the parameter otherwise."""
        where = f"parameter {self.name!r}"
        if self.kind == "bool":
            if isinstance(value, bool):
                return value
            raise CommandError(f"{where} must be true or false (got {value!r})")
        if self.kind == "choice":
            if isinstance(value, str) and value in self.choices:
                return value
            raise CommandError(f"{where} must be one of {list(self.choices)} (got {value!r})")
        # numbers: reject bools (a JSON true is not a number here), NaN and out-of-range values
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise CommandError(f"{where} must be a number (got {value!r})")
        try:
            v = float(value)
        except OverflowError:  # a JSON integer beyond float range
            raise CommandError(f"{where} must be in [{self.lo:g}, {self.hi:g}] (got a {len(str(value))}-digit "
                               "number)") from None
        if not math.isfinite(v) or v < self.lo or v > self.hi:
            raise CommandError(f"{where} must be in [{self.lo:g}, {self.hi:g}] (got {value!r})")
        if self.kind == "int":
            if not v.is_integer():
                raise CommandError(f"{where} must be an integer (got {value!r})")
            return int(v)
        return v

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "label": self.label, "kind": self.kind, "default": self.default, "lo": self.lo,
                "hi": self.hi, "step": self.step, "choices": list(self.choices), "live": self.live,
                "help": self.help}
